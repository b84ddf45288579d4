"""synchronous=NORMAL for dry runs: WAL still keeps every committed point when the process is
killed (only a power cut, which no test can make, may lose the last ones); hardware stays FULL."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

from labcal.store.journal import Journal

WRITER = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    from labcal.store.journal import Journal, Manifest, PointRecord
    journal = Journal(sys.argv[1], durable=False)
    run_id = journal.start_run(Manifest(run_dir="r", plan_name="p", plan_text="t", station_text="s",
                                        software_version="0", settings={}, metadata={}))
    for seq in range(int(sys.argv[2])):
        journal.record_point(run_id, PointRecord(
            seq=seq, replicate=1, y_deg=0, u_deg=0, pitch_deg=seq, roll_deg=0, pitch_read=seq,
            roll_read=0, attempt=1, status="ok", t_start=seq, t_end=seq + 1, n_samples=2, vx=1.0,
            vy=2.0, vz=3.0, sd_vx=0, sd_vy=0, sd_vz=0, temp_c=None, settle_s=1.0,
            settle_verdict="settled"), np.ones((2, 4)))
    print("committed", flush=True)
    os.kill(os.getpid(), signal.SIGKILL)  # no close, no checkpoint: the WAL holds the commits
""")


def test_a_dry_run_journal_keeps_every_committed_point_when_killed(tmp_path):
    db = tmp_path / "lab.sqlite"
    proc = subprocess.run([sys.executable, "-c", WRITER, str(db), "40"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == -signal.SIGKILL and "committed" in proc.stdout, proc.stderr
    assert (tmp_path / "lab.sqlite-wal").exists()  # the points are in the WAL, not yet in the file
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT COUNT(*), MAX(seq) FROM points").fetchone() == (40, 39)
        assert con.execute("SELECT SUM(LENGTH(samples)) FROM points").fetchone()[0] == 40 * 2 * 4 * 8


def test_only_a_dry_run_relaxes_the_fsync(tmp_path):
    def synchronous(journal: Journal) -> int:
        return journal.db.execute("PRAGMA synchronous").fetchone()[0]

    with Journal(tmp_path / "a.sqlite") as hardware, Journal(tmp_path / "b.sqlite", durable=False) as dry:
        assert synchronous(hardware) == 2 and synchronous(dry) == 1  # FULL, NORMAL
    assert os.path.exists(tmp_path / "b.sqlite")
