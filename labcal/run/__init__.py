"""The run machinery: the station interfaces, the sequencer, settling, prompts, Ctrl-C, and the
journal that holds every reading of every run.
"""
