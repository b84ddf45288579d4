"""labcal's command line from a test, one way each: the installed executable in a process of its own
(what a user runs: its start-up, its exit code, its streams), or the same command line in this process
(a new Python per command takes seconds on a loaded machine)."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

LABCAL = str(Path(sys.executable).with_name("labcal"))  # the console script installed beside this Python


def labcal(*args: str, typed: str | None = None, check: int | None = None, timeout: float = 120,
           **kw: Any) -> subprocess.CompletedProcess:
    """``labcal ARGS`` in a process of its own, without a terminal: ``typed`` is its stdin (none unless
    given), and it runs in a session of its own, so a signal meant for the tests never reaches it.
    ``check``: the exit code it must end with (its stderr is the failure's message). ``kw`` go to
    `subprocess.run` (``env``, ``cwd`` ...)."""
    if "stdin" not in kw and "input" not in kw:
        kw["input"] = typed if typed is not None else ""
    kw.setdefault("start_new_session", True)
    done = subprocess.run([LABCAL, *args], capture_output=True, text=True, timeout=timeout, **kw)
    if check is not None:
        assert done.returncode == check, done.stderr
    return done


def cli(capsys: Any, *args: str) -> tuple[int, str, str]:
    """``labcal ARGS`` in this process, read through pytest's ``capsys``: exit code, stdout, stderr."""
    from labcal.cli import main

    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def in_process(*args: str) -> tuple[int, str, str]:
    """``labcal ARGS`` in this process where no ``capsys`` is at hand (a fixture of a wider scope):
    exit code, stdout, stderr."""
    from labcal.cli import main

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


def bench_env(folder: Path, db: str, station: str = "bench-1") -> dict[str, str]:
    """The environment of a bench called ``station`` on the lab database ``db``, everything of it under
    ``folder``: its journal, an empty lab file, its data folder, no notifications; no LABCAL_* of the caller's
    leaks in."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("LABCAL_")}
    (folder / "lab.toml").touch()
    env.update(LABCAL_DB=db, LABCAL_STATION=station, LABCAL_CONFIG=str(folder / "lab.toml"),
               LABCAL_JOURNAL=str(folder / station / "journal.sqlite"), LABCAL_NOTIFY="",
               XDG_DATA_HOME=str(folder / "data"))
    return env


def as_bench(monkeypatch: Any, folder: Path, db: str, station: str = "bench-1") -> None:
    """This process as the bench `bench_env` describes, for labcal in this process (`cli`,
    `in_process`): its variables set and no other LABCAL_*, through ``monkeypatch`` (undone after
    the test)."""
    env = bench_env(folder, db, station)
    for name in [n for n in os.environ if n.startswith("LABCAL_") and n not in env]:
        monkeypatch.delenv(name)
    for name, value in env.items():
        if os.environ.get(name) != value:
            monkeypatch.setenv(name, value)


def here_at_bench(monkeypatch: Any, folder: Path, *args: str, db: str, station: str = "bench-1",
                  capture: Any = None) -> tuple[int, str, str]:
    """``labcal ARGS`` in this process as the bench `bench_env` describes (`as_bench`, undone with
    ``monkeypatch``): exit code, stdout, stderr, read through ``capture`` (pytest's capsys or capfd)
    or, without one (a module fixture), `in_process`."""
    as_bench(monkeypatch, folder, db, station)
    return in_process(*args) if capture is None else cli(capture, *args)


def at_bench(folder: Path, *args: str, db: str, station: str = "bench-1") -> subprocess.CompletedProcess:
    """``labcal ARGS`` as the bench `bench_env` describes, in a process of its own."""
    return labcal(*args, env=bench_env(folder, db, station), timeout=240)
