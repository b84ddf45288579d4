"""The fault table: every injected fault kind on every protocol, through `labcal run
--emulate` and `labcal resume` exactly as a technician runs them (in this process, real drivers on
the emulators written from the manuals). For each: did the run complete or pause, how many pauses,
points lost or doubled against the plan, and whether `labcal resume` completed.

    python tests/fault_matrix.py            # prints a Markdown table (a few minutes)

An operator who answers every remount and aborts at the first pause (the run stays resumable);
the resume confirms the mounts. Faults are placed mid-run with ``after``."""

from __future__ import annotations

import logging
import sqlite3
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from emulators import TIME_SCALE, private_file  # noqa: E402

from labcal.cli import main  # noqa: E402

PLAN_POINTS = 64  # four-mount-64
QUICK = "timeout_s = 0.1\nreconnect_s = 0.5"


def fault(device: str, kind: str, **extra: object) -> str:
    fields = "".join(f"\n{k} = {v!r}".replace("'", '"') for k, v in extra.items())
    return f'\n[[emulation.faults]]\ndevice = "{device}"\nkind = "{kind}"{fields}\n'


def kinds(device: str, status: str, move: str, fetch_or_status: str) -> dict[str, str]:
    """The common fault kinds, on a table's status reads (``status``), its moves (``move``)."""
    return {
        "no reply once": fault(device, "no-reply", after=40, match=fetch_or_status),
        "outage (5 lost)": fault(device, "no-reply", after=40, count=5, match=fetch_or_status),
        "late reply": fault(device, "late-reply", after=40, delay_s=0.3, match=fetch_or_status),
        "garbled": fault(device, "garbled", after=40, match=fetch_or_status),
        "truncated": fault(device, "truncated", after=40, match=fetch_or_status),
        "exception": fault(device, "exception", after=40, match=fetch_or_status),
        "alarm mid-move": fault(device, "alarm", after=20, match=status),
        "port closed, reopened": fault(device, "close-port", after=40, reopen_s=0.3, match=fetch_or_status),
        "port dead": fault(device, "close-port", after=40, match=fetch_or_status),
    }


SCENARIOS: dict[str, tuple[str, dict[str, str]]] = {
    "Modbus TCP (AZ)": ("az-modbus-tcp", {
        **kinds("pitch", "fc03 007E", "fc16 0058", "fc03 007E"),
        "busy 06h": fault("pitch", "exception", after=40, code=6, match="fc03 007E"),
        "lost STOP release ×3 (after an alarm)":
            fault("pitch", "alarm", after=20, match="fc03 007E")
            + fault("pitch", "lost-request", after=1, count=3, match="fc06 007D"),
    }),
    "Modbus RTU (AZ)": ("az-modbus-rtu", {
        **kinds("pitch", "fc03 007E", "fc16 0058", "fc03 007E"),
        "lost STOP release ×3 (after an alarm)":
            fault("pitch", "alarm", after=20, match="fc03 007E")
            + fault("pitch", "lost-request", after=1, count=3, match="fc06 007D"),
    }),
    "SMC100 ASCII": ("smc100-serial", {
        **kinds("pitch", "TS", "PA", "TS"),
        "lost TE after PA (20°/s)": fault("pitch", "no-reply", after=5, match="TE"),
    }),
    "SCPI (34970A, TCP)": ("az-modbus-tcp", {
        **kinds("dmm", "FETC", "FETC", "FETC"),
        "lost INIT (stale scan)": fault("dmm", "lost-request", after=40, match="^INIT"),
        "power cycle": fault("dmm", "power-cycle", after=40, match="FETC"),
    }),
    "SCPI (34970A, RS-232)": ("smc100-serial", {
        "power cycle (local until SYST:REM)": fault("dmm", "power-cycle", after=40, match="FETC"),
    }),
}


class Warnings(logging.Handler):
    """Counts the drivers' WARNING records (retries, reopened ports, late replies, failed stops)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1


def run_one(tmp: Path, station: str, extra: str) -> dict[str, object]:
    warnings = Warnings()
    logging.getLogger("labcal.drivers").addHandler(warnings)
    try:
        return {**run_and_resume(tmp, station, extra), "warnings": warnings.count}
    finally:
        logging.getLogger("labcal.drivers").removeHandler(warnings)


def run_and_resume(tmp: Path, station: str, extra: str) -> dict[str, object]:
    path = private_file(station, tmp, extra, QUICK)
    run_dir = tmp / "run"
    answers = tmp / "answers.txt"
    answers.write_text("y\ny\ny\ny\na\n")
    db = tmp / "lab.db"
    code = main(["run", "--station", str(path), "--emulate", "--time-scale", str(TIME_SCALE), "--no-report",
                 "--answers", str(answers), "--out", str(run_dir), "--db", str(db), "--json"])
    first = journal(db)
    resumed = None
    if first["status"] != "complete":
        answers.write_text("y\ny\ny\ny\ny\na\n")
        resumed = main(["resume", str(run_dir), "--answers", str(answers), "--no-report", "--db", str(db),
                        "--json"]) == 0
    final = journal(db)
    return {"exit": code, "status": first["status"], "pauses": final["pauses"],
            "lost": PLAN_POINTS - final["unique"], "doubled": final["points"] - final["unique"],
            "resumed": resumed, "retries": final["retries"]}


def journal(db: Path) -> dict[str, object]:
    with sqlite3.connect(db) as c:
        status = c.execute("SELECT status FROM runs").fetchone()[0]
        seqs = [s for (s,) in c.execute("SELECT seq FROM points WHERE status = 'ok'")]
        pauses = c.execute("SELECT COUNT(*) FROM events WHERE kind = 'pause'").fetchone()[0]
        retries = c.execute("SELECT COUNT(*) FROM events WHERE kind = 'retry'").fetchone()[0]
    return {"status": status, "points": len(seqs), "unique": len(set(seqs)), "pauses": pauses,
            "retries": retries}


def main_table() -> None:
    import contextlib
    import io

    print("| protocol | fault | first run | pauses | points lost | points doubled | resume "
          "| driver warnings |")
    print("|---|---|---|---|---|---|---|---|")
    for protocol, (station, faults) in SCENARIOS.items():
        for name, extra in faults.items():
            with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()), \
                    contextlib.redirect_stderr(io.StringIO()):
                row = run_one(Path(tmp), station, extra)
            resume = "—" if row["resumed"] is None else "completed" if row["resumed"] else "FAILED"
            print(f"| {protocol} | {name} | {row['status']} | {row['pauses']} | {row['lost']} | "
                  f"{row['doubled']} | {resume} | {row['warnings']} |", flush=True)


if __name__ == "__main__":
    main_table()
