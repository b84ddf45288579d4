"""Mount repeatability from replicates (`labcal.analysis.remounting`), checked by Monte Carlo on
readings generated here from Soto's kinematics with a known seating scatter, and through a
replicated dry run into the certificate's budget."""

from __future__ import annotations

import json

import numpy as np
from cli import cli

from labcal.analysis.kinematics import ARCSEC, Misalignment, gravity
from labcal.analysis.readings import Readings
from labcal.analysis.remounting import mount_scatter
from labcal.config.plans import load_plan

X_TRUE = np.vstack([[0.012, -0.008, 0.005], np.diag([4.99, 5.01, 5.0])])


def replicated(rng: np.random.Generator, sd_arcsec: float, replicates: int = 3, noise_v: float = 2e-5
               ) -> Readings:
    """four-mount-64 × replicates, every mounting seated with its own (e, f, k) ~ N(0, sd²)."""
    plan, _ = load_plan("four-mount-64")
    rows = np.array([(r, y, u, p, q) for r in range(1, replicates + 1) for y, u in plan.mounts
                     for p, q in plan.points], dtype=float)
    seat = rng.normal(0.0, sd_arcsec * ARCSEC, (replicates * len(plan.mounts), 3))
    e, f, k = np.repeat(seat, len(plan.points), axis=0).T
    g = gravity(*np.radians(rows[:, [3, 4, 1, 2]]).T, Misalignment(e=e, f=f, k=k))
    volts = X_TRUE[0] + g @ X_TRUE[1:] + rng.normal(0.0, noise_v, g.shape)
    return Readings(replicate=rows[:, 0].astype(int), y_deg=rows[:, 1], u_deg=rows[:, 2],
                    pitch_deg=rows[:, 3], roll_deg=rows[:, 4], volts=volts, temp_c=None)


def test_the_seating_scatter_is_estimated_without_bias():
    """60 replicated calibrations with σ = 10″ per angle and per mounting: the mean of σ̂² is σ² within
    15 % (σ̂² on 3·(R − 1)·4 = 24 df has a relative SD of √(2/24) ≈ 0.29, so the mean of 60 has 0.037:
    15 % is four of those); with no seating scatter the estimate is the noise's leftover, under 0.5″
    (one reading's 2e-5 V noise is 0.8″ at 5 V/g, averaged over 16 points and three sensors)."""
    rng = np.random.default_rng(11)
    found = [mount_scatter(replicated(rng, 10.0), X_TRUE) for _ in range(60)]
    assert all(s is not None and s.dof == 24 and s.mounts == 4 for s in found)
    variance = np.mean([(s.sd_rad / ARCSEC) ** 2 for s in found if s is not None])
    assert abs(variance / 100.0 - 1) < 0.15, variance
    quiet = [mount_scatter(replicated(rng, 0.0), X_TRUE) for _ in range(20)]
    assert np.mean([s.sd_rad / ARCSEC for s in quiet if s is not None]) < 0.5
    assert mount_scatter(replicated(rng, 10.0, replicates=1), X_TRUE) is None  # nothing seated twice


def test_the_budget_says_where_the_mount_repeatability_came_from(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text("[device]\nmount_repeat_arcsec = 10\n")
    rows = {}
    for replicates in ("1", "3"):
        run_dir = tmp_path / f"run{replicates}"
        code, _, err = cli(capsys, "run", "--sim", "--yes", "--rig", str(rig), "--replicates", replicates,
                           "--out", str(run_dir))
        assert code == 0, err
        budget = json.loads((run_dir / "certificate.json").read_text())["uncertainty_budget"]
        [rows[replicates]] = [r for r in budget["rows"] if r["source"] == "mount repeatability"]
    assert rows["1"]["type"] == "B" and "station file" in rows["1"]["note"]
    assert rows["3"]["type"] == "A" and "replicates' scatter" in rows["3"]["note"]
    assert rows["3"]["degrees_of_freedom"] == 24 and 3 < rows["3"]["standard_uncertainty"] < 20
