"""Property: every subcommand, driven with arguments generated from its own argparse parser, exits
0 or 2 with no traceback, and with --json prints nothing on stdout but one JSON document.

The arguments come from walking `labcal.cli.build_parser()`: every leaf subcommand, every option
it declares (type, choices, nargs, required), numbers at and beyond their bounds (0, 1, negative,
huge, inf, nan, empty, not a number), and paths that are good files of the right kind, other files,
folders, missing, or unwritable. Runs in-process (`labcal.cli.main`), so an example costs
milliseconds unless it does real work (a run, a report).

`LABCAL_PROPERTY_EXAMPLES=N` runs N examples instead of the suite's small number, and
`LABCAL_PROPERTY_SUMMARY=FILE` writes how many command lines ran and the distinct failures found
(used for the issue's figures).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import sys
import traceback
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labcal.cli import build_parser, main

EXAMPLES = int(os.environ.get("LABCAL_PROPERTY_EXAMPLES", "120"))
PER_EXAMPLE_S = 60  # a hang is a failure too (SIGALRM), never a stuck suite
SKIPPED_COMMANDS = {("sim", "serve")}  # serves until a signal: covered by tests/commands/test_station_cli.py
SKIPPED_OPTIONS = {"--emulate", "--answers", "--yes", "--help"}  # run/resume always get --yes
FORCED = {"run": ["--yes"], "resume": ["--yes"]}

NUMBERS = ["0", "1", "-1", "2", "-5", "0.5", "1.5", "90", "200", "360", "1e308", "-1e308", "inf", "-inf",
           "nan", "", "abc", "1e-300", "4", "10"]
INTEGERS = ["0", "1", "-1", "2", "3", "4", "5", "16", "101", "1000000", "", "1.5", "abc", "-5"]


def leaf_parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(path, parser) of every subcommand that runs something."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, child in subs[0].choices.items():
        yield from leaf_parsers(child, (*path, name))


LEAVES = [(p, parser) for p, parser in leaf_parsers(build_parser()) if p not in SKIPPED_COMMANDS]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """Files of every kind the commands read: good ones, and a completed and a stopped run."""
    root = tmp_path_factory.mktemp("lab")
    old = os.environ.get("LABCAL_DB")
    os.environ["LABCAL_DB"] = str(root / "lab.sqlite")
    stdin = sys.stdin
    try:
        sys.stdin = io.StringIO("")
        assert main(["run", "--sim", "--yes", "--seed", "1", "--out", str(root / "done")]) == 0
        sys.stdin = io.StringIO("y\nq\n")  # confirm the first mount, then stop at the second prompt
        assert main(["run", "--sim", "--no-report", "--out", str(root / "stopped")]) == 1
    finally:
        sys.stdin = stdin
        if old is None:
            del os.environ["LABCAL_DB"]
        else:
            os.environ["LABCAL_DB"] = old
    (root / "volts.csv").write_text("vx,vy,vz\n0.01,0.02,5.0\n0,0,0\n5,0,0\n1e308,0,0\n2.5,2.5,2.5\n")
    (root / "truth.toml").write_text("B = [0.01, 0, 0]\nS = [[5, 0, 0], [0, 5, 0], [0, 0, 5]]\n")
    (root / "garbage.txt").write_text("not, a, [valid file\n\x00")
    (root / "folder").mkdir()
    (root / "fresh").mkdir()
    (root / "readonly").mkdir(mode=0o555)
    return root


def string_values(lab: Path, dest: str, option: str) -> tuple[list[str], list[str]]:
    """(values that fit this option, values that do not) for a string-valued option."""
    done = lab / "done"
    good = {
        "readings": [str(done / "readings.csv")],
        "cert": [str(done / "fit.json"), str(done / "certificate.json")],
        "csv": [str(lab / "volts.csv")],
        "plan": ["four-mount-64", "one-mount-16", str(done / "plan.toml")],
        "station": ["lab-example", "smc100-tcp"], "run": [str(lab / "stopped"), str(done)],
        "run_dir": [str(done)], "truth": [str(lab / "truth.toml")], "serial": ["SIMULATED", "ACC-1"],
        "misalign": ["a=0.3,b=-0.2", "e=0.1"], "at": ["10,20", "-30,100", "10,20,90,0", "10,20,180,0"],
        "extend": ["harmonics", "temperature", "harmonics,temperature", "nope"],
        "pitch": ["-20,0,20", "0", "-90,90"], "operator": ["A. Tech"], "name": ["my-plan"],
    }.get(dest, [])
    fresh = str(lab / "fresh" / f"{dest}-{os.urandom(4).hex()}")
    if dest in ("out", "plot", "db"):
        good = [fresh + {"plot": ".png", "db": ".sqlite"}.get(dest, ".toml" if "generate" in option else "")]
    bad = ["", "-", str(lab / "garbage.txt"), str(lab / "folder"), str(lab / "missing" / "x"),
           str(lab / "readonly" / "x"), str(lab / "garbage.txt" / "x"), str(lab / "volts.csv"),
           str(done / "readings.csv"), "nan", "1e308", "[certificate]", "../" * 3]
    return good, bad


def value_strategy(lab: Path, action: argparse.Action, where: str) -> st.SearchStrategy[list[str]]:
    """The words one occurrence of this option takes (without the option string)."""
    if action.nargs == 0:
        return st.just([])
    if action.choices is not None:
        one = st.one_of(st.sampled_from(sorted(action.choices)), st.sampled_from(["", "x"]))
    elif action.type is int:
        one = st.sampled_from(INTEGERS)
    elif action.type is float:
        one = st.one_of(st.sampled_from(NUMBERS), st.floats(allow_nan=True, allow_infinity=True).map(repr))
    else:
        good, bad = string_values(lab, action.dest, where)
        one = st.one_of(st.sampled_from(good), st.sampled_from(bad)) if good else st.sampled_from(bad)
    count = action.nargs if isinstance(action.nargs, int) else 1
    return st.lists(one, min_size=count, max_size=count)


@st.composite
def command_lines(draw, lab: Path) -> list[str]:
    path, parser = draw(st.sampled_from(LEAVES))
    argv = [*path, *FORCED.get(path[0], [])]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or set(action.option_strings) & SKIPPED_OPTIONS:
            continue
        if not action.option_strings:  # positional: always
            argv += draw(value_strategy(lab, action, " ".join(path)))
        elif action.required or draw(st.booleans()):
            words = draw(value_strategy(lab, action, " ".join(path)))
            # `--opt=value` keeps a value that starts with '-' from reading as an option
            argv += [f"{action.option_strings[-1]}={words[0]}"] if len(words) == 1 else \
                [action.option_strings[-1], *words]
    return argv


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang(f"no answer within {PER_EXAMPLE_S} s")


def failure_of(argv: list[str], capsys) -> str | None:
    """None if the command behaved, else a signature of what went wrong (its exception and where)."""
    capsys.readouterr()
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(PER_EXAMPLE_S)
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: usage and one line on stderr, exit 2
        code = exc.code
    except BaseException as exc:  # noqa: BLE001 - a traceback is what this test looks for
        frames = traceback.extract_tb(exc.__traceback__)
        inner = next((f for f in reversed(frames) if "/labcal/" in f.filename or "/site-packages/" not in
                      f.filename), frames[-1])
        return f"{' '.join(argv[:2])}: {type(exc).__name__} at {Path(inner.filename).name}:{inner.lineno}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    captured = capsys.readouterr()
    if code not in (0, 2):
        return f"{argv[0]}: exit code {code}"
    if "Traceback" in captured.err:
        return f"{argv[0]}: traceback on stderr"
    if "--json" in argv and (code == 0 or captured.out.strip()):  # exit 2 may still print its result
        try:
            json.loads(captured.out)
        except ValueError:
            command = " ".join(a for a in argv[:2] if not a.startswith("-"))
            return f"{command}: --json stdout is not one JSON document"
    return None


def test_every_generated_command_line_exits_0_or_2_without_a_traceback(lab, capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    failures: dict[str, list[str]] = {}
    ran = []

    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck),
              derandomize="LABCAL_PROPERTY_EXAMPLES" not in os.environ)  # the suite's run is repeatable
    @given(command_lines(lab))
    def check(argv):
        monkeypatch.setattr(sys, "stdin", io.StringIO("vx,vy,vz\n0.01,0.02,5.0\n"))
        ran.append(argv)
        if (failure := failure_of(argv, capsys)) is not None:
            failures.setdefault(failure, []).append(" ".join(argv))

    check()
    summary = os.environ.get("LABCAL_PROPERTY_SUMMARY")
    if summary:
        Path(summary).write_text(json.dumps({"command_lines": len(ran), "distinct_failures": len(failures),
                                             "failures": {k: v[:3] for k, v in failures.items()}}, indent=2))
    assert not failures, "\n".join(f"{k}  e.g. labcal {v[0]}" for k, v in failures.items())
