"""Speed of the uncertainty engine (issue: fit < 0.5 s; attitude ≥ 1e6 rows/s closed form and
≥ 1e5 rows/s on the sphere), each attitude method against a per-row scipy solver in the same run.

Usage: python benchmarks/uncertainty_speed.py
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares as scipy_least_squares

from labcal.analysis.attitude import Calibration, closed_form, sphere_least_squares
from labcal.analysis.design import grid, make_plan
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import gravity
from labcal.config.emulation import InstrumentTruth
from labcal.sim.direct import simulate_readings

TRUTH = InstrumentTruth.from_coning(b=[0.0123, -0.0081, 0.0047], sensitivity=[4.9871, 5.0124, 4.9958],
                                    omega_deg=[0.21, 0.14, 0.09], azimuth_deg=[35, -120, 200])


def best_of(n: int, fn) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    plan = make_plan("tripp-481", "", grid(-180, 180, 10, -180, 180, 30), four_mounts=False, replicates=6)
    readings = simulate_readings(plan, TRUTH, noise_v=1e-5, seed=1)
    t_fit = best_of(5, lambda: fit_readings(readings).to_json())
    print(f"fit + full statistics, 6 × 481 = {len(readings)} points: {t_fit * 1e3:.1f} ms (target < 500 ms)")

    fit = fit_readings(readings)
    doc = fit.to_json()
    cal = Calibration(fit.coefficients, np.array(doc["covariance"])[:, :4, :4], np.array(doc["reading_sd"]),
                      int(min(doc["uncertainty_dof"])))
    rng = np.random.default_rng(0)
    n = 1_000_000
    pitch, roll = rng.uniform(-85, 85, n), rng.uniform(-180, 180, n)
    volts = TRUTH.static_volts(gravity(np.radians(pitch), np.radians(roll), 0, 0))
    volts += rng.normal(0, 1e-5, (n, 3))

    t_cf = best_of(3, lambda: closed_form(cal, volts))
    t_ls = best_of(3, lambda: sphere_least_squares(cal, volts[:200_000])) / 200_000 * n

    n_loop = 300
    S, B = cal.X[1:], cal.X[0]

    def per_row() -> None:
        for v in volts[:n_loop]:
            g = np.linalg.solve(S.T, v - B)
            z0 = [np.arcsin(np.clip(g[0], -1, 1)), np.arctan2(g[1], g[2])]
            scipy_least_squares(lambda z, v=v: (B + np.array([np.sin(z[0]), np.cos(z[0]) * np.sin(z[1]),
                                                              np.cos(z[0]) * np.cos(z[1])]) @ S - v)
                                / cal.reading_sd, z0, method="lm")
    t_loop = best_of(3, per_row) / n_loop * n
    rate = {"closed form": n / t_cf, "sphere WLS": n / t_ls, "scipy per row": n / t_loop}
    for name, r in rate.items():
        print(f"attitude, {name}: {r:,.0f} rows/s")
    loop = rate["scipy per row"]
    print(f"ratios against the per-row scipy loop: closed form {rate['closed form'] / loop:.0f}×, "
          f"sphere WLS {rate['sphere WLS'] / loop:.0f}× (targets: ≥ 1,000,000 and ≥ 100,000 rows/s)")


if __name__ == "__main__":
    main()
