"""What a finished run issues: the certificate, the report and the instrument's history.

Documents read finished runs from the journal; they never import the sequencer.
"""
