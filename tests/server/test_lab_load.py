"""The load benchmark (benchmarks/lab_load.py) in small: three paced stations into one
`labcal serve` and one private PostgreSQL while its client polls the API 10×/s and holds an event
stream per run. Every reading each station journaled is in PostgreSQL exactly once with equal
values, no request failed, and each stream brought each point of its run once.

The expected counts are worked out here from the plan (one-mount-16: 16 points, one replicate, as
`sequences/one-mount-16.toml` lists them); the benchmark reads the journals with sqlite3 and the
server with psycopg, never through labcal."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from services import _pg_bin, missing

BENCHMARK = Path(__file__).resolve().parent.parent.parent / "benchmarks" / "lab_load.py"
STATIONS, POINTS = 3, 16  # one-mount-16: 16 articulations, one mount, one replicate


@pytest.mark.slow
def test_three_paced_stations_under_polling_lose_and_double_nothing():
    if not _pg_bin("initdb") or not _pg_bin("pg_ctl"):
        missing("PostgreSQL", "apt-get install postgresql (Debian), or skip these tests")
    # pace 200: 476 rig seconds in about 2.4 s per run, so the polling overlaps every run's points
    done = subprocess.run([sys.executable, str(BENCHMARK), "--stations", str(STATIONS), "--plan",
                           "one-mount-16", "--pace", "200", "--sse", "--limit", "45", "--json"],
                          capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    result = json.loads(done.stdout)
    readings = result["readings"]
    assert readings["journaled"] == readings["in_postgresql"] == STATIONS * POINTS
    assert [readings[k] for k in ("lost", "doubled", "different", "unexpected")] == [0, 0, 0, 0]
    assert result["stations_failed"] == [] and result["all_done_within_limit"]
    assert result["lab_server"]["errors"] == 0 and result["lab_server"]["requests"] > 0
    assert sorted(run["station"] for run in result["runs"]) == [f"bench-{n + 1}" for n in range(STATIONS)]
    assert all(run["status"] == "complete" for run in result["runs"])
    assert len(result["streamed"]) == STATIONS
    assert all(s == {"points": POINTS, "distinct": POINTS} for s in result["streamed"].values())


def test_the_benchmark_counts_readings_lost_doubled_different_and_unexpected():
    """The comparison the benchmark exits 1 on, on rows made here: run "a" journaled seq 0, 1, 2;
    the server has 0 twice, 1 with another vx, no 2, and a seq 7 no journal has."""
    sys.path.insert(0, str(BENCHMARK.parent))
    from lab_load import compare

    journal = {("a", 0): (0, 1.0), ("a", 1): (1, 2.0), ("a", 2): (2, 3.0)}
    server = [("a", 0, 1.0), ("a", 0, 1.0), ("a", 1, 2.5), ("a", 7, 9.0)]
    assert compare(journal, server) == {"journaled": 3, "in_postgresql": 4, "lost": 1, "doubled": 1,
                                        "different": 1, "unexpected": 1}
    assert compare(journal, [("a", 2, 3.0), ("a", 0, 1.0), ("a", 1, 2.0)]) == {
        "journaled": 3, "in_postgresql": 3, "lost": 0, "doubled": 0, "different": 0, "unexpected": 0}
