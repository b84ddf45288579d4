"""How the benchmarks run a command: as its own process, with labcal's bytecode cached.

An installed labcal has its modules compiled (pip compiles a wheel's modules when it installs
them). A shell with PYTHONDONTWRITEBYTECODE=1 and an editable install would instead compile every
labcal module a process imports, in every process, a cost no installed copy pays; so each
benchmark process runs with a temporary PYTHONPYCACHEPREFIX, written by its first (warm-up) run.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import time

BYTECODE = tempfile.mkdtemp(prefix="labcal-bench-pycache-")
ENV = {**{k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"},
       "PYTHONPYCACHEPREFIX": BYTECODE}


def measure(argv: list[str]) -> tuple[float, float]:
    """Wall seconds and peak resident MiB (ru_maxrss from os.wait4) of one process, output discarded."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"{argv[:3]} failed: {proc.stderr.read().decode()[-500:]}")
    return wall, usage.ru_maxrss / 1024
