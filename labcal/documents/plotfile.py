"""A figure written where the user asked (`--plot FILE`): a folder that does not exist or a
suffix matplotlib cannot write is one line, checked before anything is drawn where possible."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.errors import LabcalError

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def check_folder(path: str | Path) -> None:
    """Refuse a plot file whose folder does not exist, before drawing anything for nothing."""
    if not Path(path).parent.is_dir():
        raise LabcalError(f"{path}: cannot write the plot (no folder {Path(path).parent})")


def save(fig: Figure, path: str | Path, **options: Any) -> None:
    """``fig.savefig(path, **options)``, its failures as one line that says what to do."""
    try:
        fig.savefig(path, **options)
    except OSError as exc:
        raise LabcalError(f"{path}: cannot write the plot ({exc.strerror or exc})") from None
    except ValueError as exc:  # matplotlib: a suffix that is no format it writes
        raise LabcalError(f"{path}: cannot write the plot ({exc}); name it .png, .pdf or .svg") from None
