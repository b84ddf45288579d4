"""The duration a run is estimated to take on the rig's clock (issue 26, Commands): one figure,
the one `--dry-run` prints, kept in run.json and in `labcal run --json` as estimated_rig_time_s
beside the rig time the run took."""

from __future__ import annotations

import json

import pytest
from emulators import TIME_SCALE, cli, private_file


@pytest.mark.parametrize("station", ["--sim", "az-modbus-tcp"])
def test_the_estimate_is_the_dry_runs_and_is_kept_beside_the_actual(station, tmp_path, capsys):
    where = ["--sim"] if station == "--sim" else ["--station", str(private_file(station, tmp_path)),
                                                   "--emulate", "--time-scale", str(TIME_SCALE)]
    code, out, _ = cli(capsys, "run", *where, "--seed", "4", "--dry-run", "--json")
    assert code == 0
    dry = json.loads(out)
    assert dry["estimated_rig_time_s"] == dry["total_s"] > 0
    assert dry["total_s"] == pytest.approx(sum(dry[f"{part}_s"] for part in
                                               ("moves", "settling", "averaging", "mounting")), rel=1e-12)
    code, out, _ = cli(capsys, "run", *where, "--seed", "4", "--yes", "--no-report", "--json",
                       "--out", str(tmp_path / "run"))
    assert code == 0
    run = json.loads(out)
    assert run["estimated_rig_time_s"] == dry["total_s"]  # the same figure, not a second estimate
    assert run["simulated_rig_time_s"] > 0
    kept = json.loads((tmp_path / "run" / "run.json").read_text())
    assert kept["estimated_rig_time_s"] == dry["total_s"]
