"""When has the reading settled? A dead time from the sensor's time constant, then a statistical
test on a moving window (hardware_protocols.md §4.3).

What biases a point is the transient left in the *window mean*. The tables stop with the output
trailing them by the first-order lag integrated along the move (`labcal.run.motion`), Δv; from the
end of the motion it fades as Δv·e^{−t/τ}, so a window of N samples dt apart that starts t_w after
the stop carries a bias Δv·e^{−t_w/τ}·m, with m = mean over the window of e^{−(i+½)·dt/τ}. The
dead time is the t_w at which that bias is the noise of the mean, σ/√N: no test on noisy samples
could resolve a smaller transient, and a larger one would bias the point. It runs from the motion's
end, so the clamp overlaps it. Then a window is accepted when, on every channel, (1) its
least-squares slope is not significantly different from zero, (2) its two half-window means agree,
and (3) its scatter is consistent with the noise model: the safety net for a sensor slower than
its settings say. The accepted window is the measurement, so settling costs no averaging time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.distributions import chi2_quantile
from labcal.config.settings import SettleSettings
from labcal.run.station import Clock, Scan, Voltmeter


@dataclass(frozen=True)
class Verdict:
    settled: bool
    reason: str  # which test failed, or "settled"


def window_fade(settings: SettleSettings, sample_s: float) -> float:
    """m: the mean of e^{−(i+½)·dt/τ} over a window of N samples dt apart (1 when dt is unknown)."""
    i = np.arange(settings.samples) + 0.5
    return float(np.mean(np.exp(-i * sample_s / settings.tau_s)))


def dead_time(transient_v: ArrayLike, settings: SettleSettings, sample_s: float = 0.0) -> NDArray | float:
    """τ·ln(Δv·m/(σ/√N)), at least 0: how long after the motion ends a window must start for the
    transient Δv left at the stop to bias its mean by no more than σ/√N."""
    target = settings.noise_v / math.sqrt(settings.samples)
    ratio = np.asarray(transient_v, dtype=float) * window_fade(settings, sample_s) / target
    t = settings.tau_s * np.log(np.maximum(ratio, 1.0))
    return t if t.ndim else float(t)


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
    sample_s: float  # the voltmeter's time per sample, as measured on this window


def dwell(dmm: Voltmeter, clock: Clock, transient_v: float, settings: SettleSettings,
          motion_end: float | None = None, sample_s: float = 0.0) -> Dwell:
    """Wait until the dead time after ``motion_end`` (by default now, the in-position time) has
    passed, then slide a window by half its length until it passes or the maximum dwell is reached
    (then the last window is returned with the failing verdict). ``sample_s``: the voltmeter's time
    per sample if known (0: the dead time assumes no fading within the window)."""
    t0 = clock.now()
    if settings.fixed_dwell_s is not None:
        clock.sleep(settings.fixed_dwell_s)
        t_read = clock.now()
        scan = dmm.read(settings.samples)
        return Dwell(scan, clock.now() - t0, Verdict(True, f"fixed dwell {settings.fixed_dwell_s:g} s"),
                     (clock.now() - t_read) / settings.samples)
    start = t0 if motion_end is None else min(motion_end, t0)
    clock.sleep(start + float(dead_time(transient_v, settings, sample_s)) - t0)
    n, half = settings.samples, settings.samples // 2
    t_read = clock.now()
    scan = dmm.read(n)
    sample_s = (clock.now() - t_read) / n
    while True:
        verdict = window_verdict(scan.volts, settings.noise_v, settings.k_sigma)
        if verdict.settled or clock.now() - t0 >= settings.max_dwell_s:
            return Dwell(scan, clock.now() - t0, verdict, sample_s)
        more = dmm.read(half)
        scan = Scan(np.concatenate([scan.volts[half:], more.volts]),
                    None if scan.temp_c is None else np.concatenate([scan.temp_c[half:], more.temp_c]))
