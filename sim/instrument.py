"""The simulated three-axis accelerometer instrument: true B and S, and its imperfections.

The model is data a station file's ``[emulation.rig]`` table holds, so it lives with the other
configuration models in `labcal.config.emulation`; the simulator imports it from here.
"""

from labcal.config.emulation import InstrumentTruth, coning_axes, default_instrument

__all__ = ["InstrumentTruth", "coning_axes", "default_instrument"]
