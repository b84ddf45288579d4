"""labcal — calibration of three-axis accelerometer attitude instruments (Soto 2020; Tripp & Tcheng 1999)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("labcal")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
