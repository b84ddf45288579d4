"""labcal — calibration of three-axis accelerometer attitude instruments (Soto 2020; Tripp & Tcheng 1999)."""


def __getattr__(name: str) -> str:
    """``labcal.__version__``, read from the installed metadata when first asked: importing
    importlib.metadata costs every command, `--help` included, more than the rest of the parser."""
    if name != "__version__":
        raise AttributeError(f"module 'labcal' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("labcal")
    except PackageNotFoundError:  # running from a source tree that is not installed
        found = "0+unknown"
    globals()["__version__"] = found
    return found
