"""A run's directory: what people and other programs read of a run.

plan.toml (the plan that ran), run.json (which journal and run — its UUID, plan hash, serial and
start time — and how the run ended), and the exports readings.csv and fit.json. The journal stays
the source of truth: every file here is derived from it (`labcal.store.exports` writes them,
atomically), and a folder is trusted only when its run.json names the journal row it came from
(`check_identity`). Results (certificate, report, history) find a finished run through this module
without importing the sequencer.
"""

from __future__ import annotations

import json
import os
import re
from datetime import UTC, datetime
from pathlib import Path

from labcal.analysis.plan import Plan
from labcal.errors import LabcalError
from labcal.store.journal import Journal, RunRow

READINGS = "readings.csv"
FIT = "fit.json"
PLAN = "plan.toml"
RUN = "run.json"


def slug(name: str, limit: int = 60) -> str:
    """A name from a file (a plan's) made safe as one path component: letters, digits, '.', '-' and
    '_' only, no leading dot, never empty — so "../x" or "a/b" cannot move a folder anywhere."""
    text = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip(".-_")[:limit].strip(".-_")
    return text or "plan"


def new_run_dir(out: str | None, plan: Plan) -> Path:
    """Where a new run's folder goes (checked, not made: `make_run_dir` makes it once the journal has
    the run, so a database that cannot be written leaves no half-made folder behind)."""
    if out is None:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        path = Path("runs") / f"{stamp}-{slug(plan.name)}"
    else:
        path = Path(out)
    if path.exists() and not path.is_dir():
        raise LabcalError(f"{path}: exists and is not a directory; {{0}} names a new or empty run directory",
                          "out")
    if path.exists() and any(path.iterdir()):
        raise LabcalError(f"{path}: run directory exists and is not empty; choose another {{0}}", "out")
    return path


def make_run_dir(path: Path) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabcalError(f"{path}: cannot create run directory ({exc.strerror})") from None


def read_run_json(run_dir: Path) -> dict:
    try:
        info = json.loads((run_dir / RUN).read_text(encoding="utf-8"))
    except FileNotFoundError:
        if not run_dir.is_dir():
            raise LabcalError(f"{run_dir}: no such run directory (if it was deleted, `labcal export RUN_ID` "
                              "recreates it from the journal)") from None
        raise LabcalError(f"{run_dir}: not a run directory (no {RUN})") from None
    except (OSError, ValueError, RecursionError) as exc:
        raise LabcalError(f"{run_dir / RUN}: unreadable ({type(exc).__name__}: {str(exc)[:120]})") from None
    if not isinstance(info, dict):
        raise LabcalError(f"{run_dir / RUN}: unreadable (not a JSON object)")
    return info


# What run.json says about which run it shows; each must match the journal's row.
IDENTITY = ("run_uuid", "plan_sha256", "instrument_serial", "started_utc")


def identity(row: RunRow) -> dict:
    """The run's identity as run.json carries it, from the journal row."""
    return {"run_uuid": row.uuid, "run_id": row.id, "plan_sha256": row.plan_hash,
            "instrument_serial": row.instrument_serial, "started_utc": row.started_utc}


def open_run(run_dir: Path) -> tuple[dict, Journal, RunRow]:
    """run.json, its journal (open: the caller closes it) and the run's row, after checking that
    the folder shows that run: a database restored from a backup or re-created reuses run ids,
    and a folder of another run must never get this one's certificate or exports."""
    info = read_run_json(run_dir)
    if "journal" not in info or "run_id" not in info:
        raise LabcalError(f"{run_dir / RUN}: names no journal; was this run made by labcal run?")
    if (not isinstance(info["run_id"], int) or not 0 < info["run_id"] < 2**63  # an SQLite rowid
            or not isinstance(info["journal"], str)):
        raise LabcalError(f"{run_dir / RUN}: run_id or journal is not what labcal writes there")
    try:
        found = Path(info["journal"]).is_file()
    except (OSError, ValueError):  # a name too long for the filesystem, a NUL byte
        found = False
    if not found:  # never make an empty database where a path points
        raise LabcalError(f"{run_dir / RUN}: its journal {info['journal']} does not exist (moved, or on "
                          "another machine?); nothing was changed")
    journal = Journal(info["journal"])
    try:
        row = journal.run(info["run_id"])
        check_identity(run_dir, info, row)
    except BaseException:
        journal.close()
        raise
    return info, journal, row


def recorded_folder(journal: Journal, row: RunRow) -> Path:
    """The run's folder as the journal records it. Runs record it absolute, so that `labcal
    export RUN_ID` from another folder finds it; an older run recorded it as given, relative to
    the folder the run was started in, which the journal does not say. Such a one is taken only
    where a folder at that relative path here shows this very run (run.json: same journal, run id
    and identity); otherwise one line asks for --out."""
    path = Path(row.run_dir)
    if path.is_absolute():
        return path
    try:
        info = read_run_json(path)
        same_journal = Path(str(info.get("journal"))).resolve() == journal.path.resolve()
        if same_journal and info.get("run_id") == row.id:
            check_identity(path, info, row)
            return Path(os.path.abspath(path))
    except (LabcalError, OSError):
        pass
    raise LabcalError(f"run {row.id}: its folder was recorded as {row.run_dir}, relative to the folder the "
                      "run was started in, which the journal does not say; run this there, or give {0} DIR",
                      "out")


def check_identity(run_dir: Path, info: dict, row: RunRow) -> None:
    """One line when run.json and the journal row are not the same run. A folder written before
    runs had UUIDs is checked on what it has (plan hash)."""
    mine = identity(row)
    keys = [k for k in IDENTITY if k in info] if "run_uuid" in info else ["plan_sha256"]
    for key in keys:
        if key == "started_utc" and info.get("run_uuid") == row.uuid:
            continue  # the UUID already says it; older labcals wrote a second-resolution start here
        if info.get(key) != mine[key]:
            raise LabcalError(f"{run_dir / RUN}: {key} {info.get(key)!r} does not match run {row.id} of "
                              f"{info['journal']} ({mine[key]!r}); this folder belongs to another run "
                              "(was the database restored or re-created?); nothing was changed")


def points_on_disk(run_dir: Path) -> int:
    """Readings safe in the run's journal (0 when there is no journal yet)."""
    try:
        _, journal, row = open_run(run_dir)
    except LabcalError:
        return 0
    with journal:
        return len(journal.points(row.id, status="ok"))
