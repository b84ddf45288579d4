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

Model settling (``mode = "model"``, opt-in) does not wait for the transient to fade below the
noise: it samples from the moment the tables are in position and fits c + a_k·e^{−t/τ} to every
channel k, with τ shared by the channels and *estimated* from the record (the configured τ only
centres the search). The point is the fitted settled value c, accepted when its standard error is
at most σ/√N (as precise as a conventional window), the residuals are consistent with the noise
model (χ²), τ lies inside its search range, and the fitted transient left at the record's end is
at most EXTRAPOLATE_MAX·σ/√N (so a tail-shape error of a fraction f biases c by at most f·that).
A sensor that does not follow one exponential fails these tests; the mode then falls back to
conventional settling, whose first window is the record's last N samples, so a detected mismatch
costs no more than waiting (benchmarks/settle_model.py validates it). What no record this short
can tell from the settled value is a second, *slower* pole too small to bend the fit (0.01–0.1 %
of the step at 3τ): it biases the point by what is left of it at the record's end — more than
waiting would, which stops later on the same tail.
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
    estimate: tuple[NDArray, NDArray] | None = None  # model settling: (settled V, its SE·√n) per channel


def dwell(dmm: Voltmeter, clock: Clock, transient_v: float, settings: SettleSettings,
          motion_end: float | None = None, sample_s: float = 0.0, first: Scan | None = None) -> Dwell:
    """Wait until the dead time after ``motion_end`` (by default now, the in-position time) has
    passed, then slide a window by half its length until it passes or the maximum dwell is reached
    (then the last window is returned with the failing verdict). ``sample_s``: the voltmeter's time
    per sample if known (0: the dead time assumes no fading within the window). ``first``: the
    first window, already read after the dead time (model settling's fallback)."""
    t0 = clock.now()
    if settings.fixed_dwell_s is not None:
        clock.sleep(settings.fixed_dwell_s)
        t_read = clock.now()
        scan = dmm.read(settings.samples)
        return Dwell(scan, clock.now() - t0, Verdict(True, f"fixed dwell {settings.fixed_dwell_s:g} s"),
                     (clock.now() - t_read) / settings.samples)
    start = t0 if motion_end is None else min(motion_end, t0)
    n, half = settings.samples, settings.samples // 2
    if first is None:
        clock.sleep(start + float(dead_time(transient_v, settings, sample_s)) - t0)
        t_read = clock.now()
        first = dmm.read(n)
        sample_s = (clock.now() - t_read) / n
    scan = first
    while True:
        verdict = window_verdict(scan.volts, settings.noise_v, settings.k_sigma)
        if verdict.settled or clock.now() - t0 >= settings.max_dwell_s:
            return Dwell(scan, clock.now() - t0, verdict, sample_s)
        more = dmm.read(half)
        scan = Scan(np.concatenate([scan.volts[half:], more.volts]),
                    None if scan.temp_c is None else np.concatenate([scan.temp_c[half:], more.temp_c]))


EXTRAPOLATE_MAX = 10.0  # the fitted transient left at the record's end, in σ/√N, at most
TAU_RANGE = (0.2, 5.0)  # τ is searched between these multiples of the configured τ


@dataclass(frozen=True)
class TailFit:
    settled_v: NDArray  # c per channel
    se_v: NDArray  # its standard error (σ from the noise model)
    left_v: NDArray  # |a·e^{−t/τ}| at the last sample, per channel
    tau_s: float  # estimated
    verdict: Verdict


def _tail_rss(volts: NDArray, t: NDArray, taus: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """For each τ: the residual sum of squares of the per-channel least-squares c + a·e^{−t/τ},
    and c, a ((τ, channel) arrays), from the 2×2 normal equations."""
    e = np.exp(-t[None, :] / taus[:, None])  # (τ, n)
    n, se, see = len(t), e.sum(axis=1), (e * e).sum(axis=1)
    sy, sey = volts.sum(axis=0), e @ volts  # (channel,), (τ, channel)
    det = n * see - se**2
    a = (n * sey - se[:, None] * sy[None, :]) / det[:, None]
    c = (sy[None, :] - a * se[:, None]) / n
    resid = volts[None, :, :] - c[:, None, :] - a[:, None, :] * e[:, :, None]
    return np.einsum("tnk,tnk->t", resid, resid), c, a


def _fit(volts: NDArray, t: NDArray, noise_v: float, tau_guess: float):
    """c, a (per channel), τ, the parameters' covariance (c_1, a_1, …, c_k, a_k, τ; σ from the
    noise model), the RSS, and whether τ fell on the search range's edge. τ by variable
    projection: the RSS on a log grid, refined by golden section between the grid neighbours of
    its minimum; the covariance from the linearised Jacobian."""
    n, k = volts.shape
    grid = tau_guess * np.geomspace(*TAU_RANGE, 97)
    best = int(np.nanargmin(_tail_rss(volts, t, grid)[0]))
    lo, hi = np.log(grid[max(best - 1, 0)]), np.log(grid[min(best + 1, len(grid) - 1)])
    golden = (math.sqrt(5) - 1) / 2
    for _ in range(40):  # golden section on log τ: ~1e-8 of the bracket
        x1, x2 = hi - golden * (hi - lo), lo + golden * (hi - lo)
        r = _tail_rss(volts, t, np.exp([x1, x2]))[0]
        lo, hi = (lo, x2) if r[0] <= r[1] else (x1, hi)
    tau = float(np.exp((lo + hi) / 2))
    rss, c, a = (x[0] for x in _tail_rss(volts, t, np.array([tau])))
    e = np.exp(-t / tau)
    jac = np.zeros((n * k, 2 * k + 1))
    for ch in range(k):
        rows = slice(ch * n, (ch + 1) * n)
        jac[rows, 2 * ch], jac[rows, 2 * ch + 1] = 1.0, e
        jac[rows, -1] = a[ch] * t / tau**2 * e
    cov = noise_v**2 * np.linalg.pinv(jac.T @ jac)
    return c, a, tau, cov, float(rss), best in (0, len(grid) - 1)


def fit_tail(volts: NDArray, sample_s: float, noise_v: float, tau_guess: float, samples: int) -> TailFit:
    """Fit c + a_k·e^{−t/τ} (τ shared) to an (n, channels) record of samples ``sample_s`` apart and
    judge it (module docstring)."""
    n, k = volts.shape
    t = (np.arange(n) + 0.5) * sample_s
    c, a, tau, cov, rss, at_edge = _fit(volts, t, noise_v, tau_guess)
    se = np.sqrt(np.abs(np.diag(cov)[0:2 * k:2]))
    left = np.abs(a) * math.exp(-t[-1] / tau)
    target = noise_v / math.sqrt(samples)
    if at_edge:
        verdict = Verdict(False, "model: τ outside its search range")
    elif rss / noise_v**2 > chi2_quantile(0.999, n * k - (2 * k + 1)):
        verdict = Verdict(False, "model: residuals above the noise model")
    elif np.any(se > target):
        verdict = Verdict(False, "model: settled value not yet precise enough")
    elif np.any(left > EXTRAPOLATE_MAX * target):
        verdict = Verdict(False, "model: too much transient left to extrapolate")
    else:
        verdict = Verdict(True, f"settled (model, τ = {tau:.3g} s)")
    return TailFit(c, se, left, tau, verdict)


def dwell_model(dmm: Voltmeter, clock: Clock, transient_v: float, settings: SettleSettings,
                motion_end: float | None = None, sample_s: float = 0.0) -> Dwell:
    """Model settling: sample from now (in position), fit the tail after every fifth of a window, and
    return the fitted settled value once `fit_tail` accepts it; if it has not by the time a
    conventional window (from the dead time after ``motion_end``) would end, the record's last N
    samples are that window and `dwell` goes on from it: a mismatch costs no more than waiting.
    The verdict says why it waited."""
    t0 = clock.now()
    start = t0 if motion_end is None else min(motion_end, t0)
    n, more_n = settings.samples, max(settings.samples // 5, 1)  # refit every fifth of a window
    window_start = start + float(dead_time(transient_v, settings, sample_s))
    if window_start <= t0 + n * sample_s:  # no time to win: wait as usual
        return dwell(dmm, clock, transient_v, settings, motion_end, sample_s)
    t_read = clock.now()
    scan = dmm.read(max(n, 8))
    sample_s = (clock.now() - t_read) / len(scan.volts)
    while True:
        fit = fit_tail(scan.volts, sample_s, settings.noise_v, settings.tau_s, n)
        if fit.verdict.settled:
            m = len(scan.volts)
            return Dwell(scan, clock.now() - t0, fit.verdict, sample_s,
                         (fit.settled_v, fit.se_v * math.sqrt(m)))
        if clock.now() >= window_start + n * sample_s:  # the record's end is a conventional window
            fallback = dwell(dmm, clock, transient_v, settings, motion_end, sample_s,
                             Scan(scan.volts[-n:], None if scan.temp_c is None else scan.temp_c[-n:]))
            why = f"{fallback.verdict.reason} (waited: {fit.verdict.reason})"
            return Dwell(fallback.scan, clock.now() - t0, Verdict(fallback.verdict.settled, why),
                         fallback.sample_s)
        more = dmm.read(more_n)
        scan = Scan(np.concatenate([scan.volts, more.volts]),
                    None if scan.temp_c is None else np.concatenate([scan.temp_c, more.temp_c]))
