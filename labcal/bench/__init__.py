"""Stations assembled: a station file's devices opened through the drivers, or the simulated rig
and the emulators (the only production path into `labcal.sim`).
"""
