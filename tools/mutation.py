"""Mutation testing of the modules whose arithmetic and bytes a certificate rests on.

Run from the repository root, in the test venv with the ``mutation`` extra (mutmut 3)::

    .venv/bin/pip install -e '.[test,mutation]'
    nice -n 15 .venv/bin/python tools/mutation.py                # every module below
    nice -n 15 .venv/bin/python tools/mutation.py regression     # one (or a few) of them
    .venv/bin/python tools/mutation.py --no-run --show budget    # the last run's score and survivors
    nice -n 15 .venv/bin/python tools/mutation.py --baseline modbus  # without test_modbus_mutants.py

Not part of CI: a module takes minutes, all of them together about an hour on a busy 2-core machine.

Why a staging tree: mutmut 3 copies the sources into ``mutants/`` and names each mutant after the
file's path, so it must see the tree as the wheel installs it. Here ``drivers/`` is installed as
``labcal.drivers`` (pyproject's package-dir); mutated in place, ``drivers/modbus.py`` would be named
``drivers.modbus`` while the tests import ``labcal.drivers.modbus`` and the editable install would
hand them the unmutated file. So each module gets ``.mutation/<name>/`` holding ``labcal/`` with
``drivers/``, ``sim/``, ``sequences/`` and ``stations/`` placed where the wheel puts them, the tests, and a
pyproject whose ``[tool.mutmut]`` mutates that one file and runs only the test files that cover it
(its ``test_<name>_mutants.py`` included) — minutes, not the hours of the whole suite per mutant.
Every run starts from scratch: mutmut would keep a survivor's verdict although the tests changed.

Survivors reviewed as equivalent (no test can tell them from the original) are listed with the
reason in ``docs/mutation.md`` and keyed in ``tools/mutation_equivalents.toml`` by mutant name and
the mutated line; a key whose line no longer matches (the module changed) counts as a survivor
again until reviewed. The score printed is killed / (mutants − reviewed equivalents), where a mutant
that makes a test hang until mutmut's timeout (a wait that never ends) counts as killed.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGE = ROOT / ".mutation"
EQUIVALENTS = ROOT / "tools" / "mutation_equivalents.toml"


@dataclass(frozen=True)
class Target:
    """One module: its file as installed (inside labcal/) and the test files that exercise it (by name,
    in whichever folder of tests/ they are)."""

    installed: str
    tests: tuple[str, ...]


TARGETS: dict[str, Target] = {
    "regression": Target("labcal/analysis/regression.py",
                         ("test_regression.py", "test_statistics.py",
                          "test_gross_errors.py")),
    "budget": Target("labcal/analysis/budget.py", ("test_budget.py",)),
    # test_labdb (migrations), test_history and test_run_guard also open a journal, but spend minutes per
    # mutant on migrated databases and certificates; the journal's own tests decide its mutants.
    "journal": Target("labcal/store/journal.py", ("test_journal_truth.py", "test_journal_sync.py")),
    "modbus": Target("labcal/drivers/modbus.py",
                     ("test_modbus_frames.py", "test_az_defects.py", "test_transcripts.py",
                      "test_driver_logging.py")),
    # the stops, window checks and diagnoses are tested through both drivers
    "newport_smc100": Target("labcal/drivers/newport_smc100.py",
                             ("test_newport_smc100.py", "test_transcripts.py",
                              "test_stop_all.py", "test_axis_diagnoses.py")),
    "oriental_az": Target("labcal/drivers/oriental_az.py",
                          ("test_modbus_frames.py", "test_az_defects.py",
                           "test_transcripts.py", "test_oriental_az.py",
                           "test_stop_all.py", "test_axis_diagnoses.py")),
}

# Folders of the repository and where the wheel installs them (pyproject [tool.setuptools.package-dir]).
LAYOUT = {"labcal": "labcal", "drivers": "labcal/drivers", "sim": "labcal/sim",
          "sequences": "labcal/sequences", "stations": "labcal/stations", "tests": "tests"}


@dataclass
class Score:
    name: str
    where: Path
    killed: int = 0
    total: int = 0
    equivalent: list[str] = field(default_factory=list)
    survivors: list[str] = field(default_factory=list)  # neither killed nor reviewed as equivalent
    other: dict[str, int] = field(default_factory=dict)  # timeout, suspicious, no tests ...

    @property
    def percent(self) -> float:
        counted = self.total - len(self.equivalent)
        return 100.0 * self.killed / counted if counted else 100.0


def stage(name: str, target: Target, baseline: bool = False) -> Path:
    """Lay the installed tree out in ``.mutation/<name>/`` (``<name>-baseline/`` without the module's own
    ``_mutants`` tests: the score they started from), where ``--no-run`` finds the last run's results."""
    where = STAGE / (f"{name}-baseline" if baseline else name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    # mutmut keeps a survivor's verdict when the tests change; a run is only honest from scratch
    for dest in (*LAYOUT.values(), "mutants"):
        shutil.rmtree(where / dest, ignore_errors=True)
    for source, dest in LAYOUT.items():
        shutil.copytree(ROOT / source, where / dest, ignore=ignore, dirs_exist_ok=True)
    wanted = (*target.tests, *([] if baseline else [f"test_{name}_mutants.py"]))
    tests = [str(path.relative_to(ROOT)) for file in wanted for path in sorted((ROOT / "tests").rglob(file))]
    pyproject = (ROOT / "pyproject.toml").read_text()
    pyproject += (
        "\n[tool.mutmut]\n"
        'source_paths = ["labcal"]\n'
        f'only_mutate = ["{target.installed}"]\n'
        f"pytest_add_cli_args_test_selection = {tests!r}\n"
        # -p no:randomly and -x keep a run short; the timeout stops a mutant that loops on a socket;
        # -n 0: mutmut records which tests reach a mutant in its own process, not in xdist's workers
        'pytest_add_cli_args = ["-x", "-q", "-n", "0", "-p", "no:cacheprovider", "-p", "no:randomly"]\n'
    ).replace("'", '"')
    (where / "pyproject.toml").write_text(pyproject)
    return where


def mutmut(where: Path, *args: str, capture: bool = False) -> str:
    cmd = [sys.executable, "-m", "mutmut", *args]
    done = subprocess.run(cmd, cwd=where, text=True, check=False,
                          stdout=subprocess.PIPE if capture else None)
    if done.returncode != 0:
        raise SystemExit(f"mutation: `mutmut {' '.join(args)}` failed in {where} (exit {done.returncode})")
    return done.stdout or ""


def mutated_line(where: Path, mutant: str) -> str:
    """The line(s) a mutant adds, whitespace-squeezed: what tools/mutation_equivalents.toml keys on."""
    diff = mutmut(where, "show", mutant, capture=True)
    added = [ln[1:] for ln in diff.splitlines() if ln.startswith("+") and not ln.startswith("+++")]
    return " / ".join(" ".join(ln.split()) for ln in added)


def score(name: str, where: Path, equivalents: dict[str, dict[str, str]]) -> Score:
    result = Score(name, where)
    listing = mutmut(where, "results", "--all", "true", capture=True)
    for match in re.finditer(r"^\s+(\S+): (.+)$", listing, re.MULTILINE):
        mutant, status = match[1], match[2].strip()
        result.total += 1
        if status in ("killed", "timeout"):  # a mutant that hangs a test (waits for ever) is caught too
            result.killed += 1
            if status == "timeout":
                result.other["timeout"] = result.other.get("timeout", 0) + 1
            continue
        reviewed = equivalents.get(mutant)
        if status == "survived" and reviewed and reviewed["line"] == mutated_line(where, mutant):
            result.equivalent.append(mutant)
            continue
        result.survivors.append(mutant)
        if status != "survived":
            result.other[status] = result.other.get(status, 0) + 1
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("modules", nargs="*", metavar="MODULE",
                        help=f"one or more of {', '.join(TARGETS)} (default: all)")
    parser.add_argument("--max-children", type=int, default=2, help="parallel mutants (default 2)")
    parser.add_argument("--show", action="store_true", help="print the diff of every unreviewed survivor")
    parser.add_argument("--baseline", action="store_true",
                        help="leave out tests/test_<module>_mutants.py: the score before they were written")
    parser.add_argument("--no-run", action="store_true",
                        help="score the last run again (after reviewing equivalents) without running mutants")
    args = parser.parse_args()
    unknown = [m for m in args.modules if m not in TARGETS]
    if unknown:
        parser.error(f"unknown module {unknown[0]!r}; choose from {', '.join(TARGETS)}")
    if os.nice(0) < 15:  # the machine is shared: never compete with interactive work
        os.nice(15 - os.nice(0))
    equivalents: dict[str, dict[str, str]] = {}
    if EQUIVALENTS.exists():
        for entries in tomllib.loads(EQUIVALENTS.read_text()).values():
            equivalents.update(entries)
    scores = []
    for name in args.modules or list(TARGETS):
        if args.no_run:
            where = STAGE / (f"{name}-baseline" if args.baseline else name)
            if not (where / "mutants").exists():
                parser.error(f"no earlier run of {name} in {where}; run without --no-run first")
        else:
            where = stage(name, TARGETS[name], args.baseline)
            mutmut(where, "run", "--max-children", str(args.max_children))
        scores.append(score(name, where, equivalents))
    print(f"\n{'module':<16} {'killed':>6} {'mutants':>7} {'equiv.':>6} {'score':>7}  unreviewed survivors")
    for s in scores:
        extra = ", ".join(f"{n} {k}" for k, n in s.other.items() if k != "timeout")
        hung = f" (of which {s.other['timeout']} by timeout)" if s.other.get("timeout") else ""
        print(f"{s.name:<16} {s.killed:>6} {s.total:>7} {len(s.equivalent):>6} {s.percent:>6.1f}%  "
              f"{len(s.survivors)}{f' ({extra})' if extra else ''}{hung}")
    for s in scores:
        for mutant in s.survivors:
            print(f"  {mutant}")
            if args.show:
                print(mutmut(s.where, "show", mutant, capture=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
