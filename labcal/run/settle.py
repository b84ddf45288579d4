"""When has the reading settled? A dead time from the sensor's time constant, then a statistical
test on a moving window (hardware_protocols.md §4.3).

After a step of Δv the first-order output's transient falls below the noise of an N-sample mean,
σ/√N, after τ·ln(Δv·√N/σ). Nothing is read before that dead time: no test on noisy samples could
resolve a smaller transient, and a larger one would bias the mean. Then a window of N samples is
accepted when, on every channel, (1) its least-squares slope is not significantly different from
zero, (2) its two half-window means agree, and (3) its scatter is consistent with the noise
model. The accepted window is the measurement, so settling costs no averaging time of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.distributions import chi2_quantile
from labcal.config.settings import SettleSettings
from labcal.run.station import Clock, Scan, Voltmeter


@dataclass(frozen=True)
class Verdict:
    settled: bool
    reason: str  # which test failed, or "settled"


def dead_time(step_v: float, settings: SettleSettings) -> float:
    """τ·ln(Δv/(σ/√N)): the time for a step's transient to fall below the noise of the mean."""
    target = settings.noise_v / math.sqrt(settings.samples)
    return settings.tau_s * math.log(max(step_v / target, 1.0))


def window_verdict(volts: NDArray, noise_v: float, k_sigma: float) -> Verdict:
    """The three tests on an (n, channels) window of equally spaced samples."""
    n = len(volts)
    t = np.arange(n) - (n - 1) / 2
    slope = t @ (volts - volts.mean(axis=0)) / (t @ t)  # per sample
    slope_se = noise_v / math.sqrt(t @ t)
    if np.any(np.abs(slope) > k_sigma * slope_se):
        return Verdict(False, "drifting (slope)")
    half = n // 2
    diff = volts[:half].mean(axis=0) - volts[n - half:].mean(axis=0)
    if np.any(np.abs(diff) > k_sigma * noise_v * math.sqrt(2 / half)):
        return Verdict(False, "half-window means disagree")
    limit = noise_v * math.sqrt(chi2_quantile(0.999, n - 1) / (n - 1))
    if np.any(volts.std(axis=0, ddof=1) > limit):
        return Verdict(False, "scatter above the noise model")
    return Verdict(True, "settled")


@dataclass(frozen=True)
class Dwell:
    scan: Scan  # the accepted window: the measurement
    settle_s: float  # from in-position to the end of the window
    verdict: Verdict


def dwell(dmm: Voltmeter, clock: Clock, step_v: float, settings: SettleSettings) -> Dwell:
    """Wait out the dead time, then slide a window by half its length until it passes or the
    maximum dwell is reached (then the last window is returned with the failing verdict)."""
    t0 = clock.now()
    if settings.fixed_dwell_s is not None:
        clock.sleep(settings.fixed_dwell_s)
        scan = dmm.read(settings.samples)
        return Dwell(scan, clock.now() - t0, Verdict(True, f"fixed dwell {settings.fixed_dwell_s:g} s"))
    clock.sleep(dead_time(step_v, settings))
    n, half = settings.samples, settings.samples // 2
    scan = dmm.read(n)
    while True:
        verdict = window_verdict(scan.volts, settings.noise_v, settings.k_sigma)
        if verdict.settled or clock.now() - t0 >= settings.max_dwell_s:
            return Dwell(scan, clock.now() - t0, verdict)
        more = dmm.read(half)
        scan = Scan(np.concatenate([scan.volts[half:], more.volts]),
                    None if scan.temp_c is None else np.concatenate([scan.temp_c[half:], more.temp_c]))
