"""labcal — calibration of three-axis accelerometer attitude instruments (Soto 2020; Tripp & Tcheng 1999)."""

from typing import TYPE_CHECKING

from labcal.lazy import lazy

if TYPE_CHECKING:
    from importlib import metadata
else:
    metadata = lazy("importlib.metadata")  # start-up without importlib


def __getattr__(name: str) -> str:
    """``labcal.__version__``, read from the installed metadata when first asked: importing
    importlib.metadata costs every command, `--help` included, more than the rest of the parser."""
    if name != "__version__":
        raise AttributeError(f"module 'labcal' has no attribute {name!r}")
    try:
        found = metadata.version("labcal")
    except metadata.PackageNotFoundError:  # running from a source tree that is not installed
        found = "0+unknown"
    globals()["__version__"] = found
    return found
