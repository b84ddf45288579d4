"""How far the tables wind their cables over a dry run.

Each table's accumulated rotation from home, lowest and highest, over `labcal run --sim --yes`
(four-mount-64) and over the 481-point grid × 4 mounts (`--replicates R`, default 1). Measured at
the simulated tables themselves (every move's start and end, where a trapezoid has its extremes),
so it runs unchanged on a labcal from before cable wrap (whose tables took the shortest way round
every time) for the comparison.

Usage: python benchmarks/cable_wrap.py [--replicates R]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from labcal import cli
from labcal.analysis.design import grid, make_plan
from labcal.config.plans import plan_toml
from labcal.sim import tables

seen: dict[str, tuple[float, float]] = {}
_move = tables.SimAxis.move_to


def _recorded(self, *args, **kwargs):
    _move(self, *args, **kwargs)
    low, high = seen.get(self.name, (0.0, 0.0))
    for angle in (self._start_angle, self._start_angle + self._distance):
        low, high = min(low, angle), max(high, angle)
    seen[self.name] = (low, high)


def wound(extra: list[str]) -> dict[str, tuple[float, float]]:
    seen.clear()
    with tempfile.TemporaryDirectory() as folder:
        code = cli.main(["run", "--sim", "--yes", "--no-report", "--out", f"{folder}/run",
                         "--db", f"{folder}/lab.sqlite", *extra])
    assert code == 0
    return dict(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicates", type=int, default=1)
    args = parser.parse_args()
    tables.SimAxis.move_to = _recorded  # type: ignore[method-assign]
    results = {"four-mount-64": wound([])}
    points = grid(-90, 90, 15, 0, 350, 10) + [(0.0, float(r)) for r in range(5, 130, 10)]
    plan = make_plan("grid-481", "481 points × 4 mounts", points, four_mounts=True,
                     replicates=args.replicates)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "grid-481.toml"
        path.write_text(plan_toml(plan), encoding="utf-8")
        results[f"grid-481 × 4 mounts × {args.replicates}"] = wound(["--plan", str(path)])
    for name, tables_seen in results.items():
        print(name + ": " + ", ".join(f"{table} {low:+g}° … {high:+g}°"
                                      for table, (low, high) in tables_seen.items()))


if __name__ == "__main__":
    main()
