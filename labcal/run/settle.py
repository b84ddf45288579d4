"""When has the reading settled? A dead time from the sensor's time constant, then a statistical
test on a moving window (hardware_protocols.md §4.3).

What biases a point is the transient left in the *window mean*. The tables stop with the output
trailing them by the first-order lag integrated along the move (`labcal.run.motion`), Δv; from the
end of the motion it fades as Δv·e^{−t/τ}, so a window of N samples dt apart that starts t_w after
the stop carries a bias Δv·e^{−t_w/τ}·m, with m = mean over the window of e^{−i·dt/τ}: a sample is
counted from the start of its sweep, where a scanning DMM's first channel integrates (counted from
the sweep's middle, the first channel's first sample kept 3–9σ of transient on the emulated 34970A
and a third of the first windows failed the slope test). The
dead time is the t_w at which that bias is a tenth (``leftover``) of the noise of the mean, σ/√N:
no test on noisy samples could resolve even σ/√N, but a bias that size, always along the move, is
not noise and would belong in the budget; a tenth of it changes no expanded uncertainty. It runs
from the motion's end, so the clamp overlaps it. Then a window is accepted when, on every channel, (1) its
least-squares slope is not significantly different from zero, (2) its two half-window means agree,
and (3) its scatter is consistent with the noise model: the safety net for a sensor slower than
its settings say. The accepted window is the measurement, so settling costs no averaging time.

Model settling (``mode = "model"``, opt-in) does not wait for the transient to fade below the
noise: it samples from the moment the tables are in position and fits c_k + a_k·e^{−t/τ̂} to every
channel k. τ̂ is the instrument's, estimated once from every record of the run so far (`TailPool`;
the configured τ only centres its search), so a point fits only c and a and needs fewer samples.
The point is the fitted settled value c, accepted when its standard error (τ̂'s share included)
is at most σ/√N (as precise as a conventional window), its residuals are consistent with the
noise model (χ²), and the pool vouches for the model. What no single record can tell from the
settled value is a second, slower pole too small to bend the fit (0.01 % of the step at 3τ biases
a point by σ/(2√N) while its χ² non-centrality is ~0.4); pooled over the run's records, weighted by
their transients, it adds up, so the pool scores it and (1) a score beyond Z_DETECT is a detected
mismatch: from then on every point waits; (2) before that, a point is accepted only if the pooled
records bound the slow tail well enough: the upper confidence bound on it (the pooled estimate
plus Z_BOUND standard errors) would bias that point by at most σ/(3√N). The pool therefore needs
a hundred-odd records before it vouches for a point; a run starts with the records of the
instrument's earlier runs (`labcal.run.settle_pool`), so a 64-point plan gains from the instrument's
fourth run on, and the conventional window is the record's last N samples, so a point the
model does not settle costs no more than waiting (benchmarks/settle_model.py validates it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.distributions import chi2_quantile
from labcal.config.settings import SettleSettings
from labcal.devices.station import Clock, Scan, Voltmeter


@dataclass(frozen=True)
class Verdict:
    settled: bool
    reason: str  # which test failed, or "settled"


def window_fade(settings: SettleSettings, sample_s: float) -> float:
    """m: the mean of e^{−i·dt/τ} over a window of N sweeps dt apart (1 when dt is unknown), each
    sweep's sample taken at its start: the first channel's, the one nearest the transient."""
    i = np.arange(settings.samples)
    return float(np.mean(np.exp(-i * sample_s / settings.tau_s)))


def dead_time(transient_v: ArrayLike, settings: SettleSettings, sample_s: float = 0.0) -> NDArray | float:
    """τ·ln(Δv·m/(ℓ·σ/√N)), at least 0: how long after the motion ends a window must start for the
    transient Δv left at the stop to bias its mean by no more than ℓ·σ/√N (ℓ: ``leftover``).

    ℓ = 1 (σ/√N, the most no test on the window could resolve) left +2 to +3 µV on average in
    every reading of four-mount-64 (σ/√N = 6.3 µV), always along the move: a bias, not noise, that
    the fit cannot average out and the budget did not carry. ℓ = 0.1 keeps it below a tenth of a
    reading's noise, where leaving it out of the budget changes no expanded uncertainty, for
    τ·ln 10 (1.15 s at τ = 0.5 s) more per point after a move that leaves a transient."""
    target = settings.leftover * settings.noise_v / math.sqrt(settings.samples)
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


TAU_RANGE = (0.2, 5.0)  # τ is searched between these multiples of the configured τ
TAU_GRID = 241  # log-spaced τ at which the pooled sums are kept (1.3 % apart; τ̂ interpolated)
SLOW = 3.0  # the slow tail the pooled score looks for: e^{−t/(3τ)} (2τ…10τ leave nearly one shape)
Z_DETECT = 4.0  # |pooled score| that says the sensor has a slow tail (two-sided p ≈ 6e-5 per look)
Z_BOUND = 3.0  # a point trusts the slow tail's one-sided 99.87 % upper confidence bound
POOL_MIN = 10  # records before the pool says anything


def _line_fit(v: NDArray, e: NDArray) -> tuple[NDArray, NDArray]:
    """(c, a) of the least-squares c + a·e to each row of v (…, n), e (…, n) broadcasting."""
    n, se, see = v.shape[-1], e.sum(-1), (e * e).sum(-1)
    sv, sev = v.sum(-1), (e * v).sum(-1)
    a = (n * sev - se * sv) / (n * see - se**2)
    return (sv - a * se) / n, a


def _project_out(v: NDArray, e: NDArray) -> NDArray:
    """v (…, n) less its least-squares fit by {1, e}, row by row."""
    c, a = _line_fit(v, e)
    return v - c[..., None] - a[..., None] * e


@dataclass(frozen=True)
class PoolState:
    """What a `TailPool` knows, to carry into the instrument's next run: its sums over ``records``
    records (the grid of the τ and σ it was made with) and the mismatch it saw, if any."""

    sums: NDArray
    records: int
    mismatch: str


def _tau_of(sums: NDArray, taus: NDArray, noise_v: float) -> tuple[float, float] | None:
    """(τ̂, its SE) from pooled sums on the grid ``taus``, or None when the minimum is on its edge."""
    rss = sums[0]
    i = int(np.argmin(rss))
    if i in (0, len(taus) - 1) or sums[3, i] <= 0:
        return None
    y0, y1, y2 = rss[i - 1:i + 2]
    step = math.log(taus[1] / taus[0])
    shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) if y0 - 2 * y1 + y2 > 0 else 0.0
    return float(taus[i] * math.exp(shift * step)), noise_v / math.sqrt(sums[3, i])


def _slow_of(sums: NDArray, i: int) -> tuple[float, float]:
    """The slow tail's amplitude estimate β̂ (per unit transient) at grid τ ``i``, orthogonal to a
    change of τ, and its standard error in units of σ: (x·r − x·d·d·r/d·d)/q, 1/√q with
    q = x·x − (x·d)²/d·d."""
    xx, xd, dd, xr, dr = sums[1:, i].tolist()
    q = max(xx - xd**2 / dd, 1e-300) if dd > 0 else max(xx, 1e-300)
    return (xr - (xd * dr / dd if dd > 0 else 0.0)) / q, 1.0 / math.sqrt(q)


class TailPool:
    """What the run's records say about its instrument's tail, pooled over every point so far.

    One instrument has one τ, so it is estimated once from all the records (variable projection:
    the residual sum of squares of c_k + a_k·e^{−t/τ} per record and channel, summed over records
    on a grid of τ, its minimum interpolated), and each point then only fits c and a: fewer samples
    for the same precision. What no single record can tell from the settled value is a second,
    slower pole too small to bend it: its amplitude follows the transient, so across records its
    residual shape, e^{−t/(SLOW·τ)} less its fit by {1, e^{−t/τ}}, weighted by each record's a,
    adds up coherently while the noise does not. The pooled score for it (orthogonal to a change of
    τ, which also absorbs part of it) is z; |z| ≥ Z_DETECT is a detected mismatch, after which the
    pool never vouches for a point again. Before that, a point is settled by the model only if the
    slow tail that would bias it by σ/(3√N) lies beyond the records' upper confidence bound, i.e.
    would show at z ≥ |z| + Z_BOUND: until it does, points wait.

    A pool may start with the records of the instrument's earlier runs (``history``, kept in the lab
    database by `labcal.run.settle_pool`): they count as the run's own, and a mismatch they saw
    stays seen. Once the run has POOL_MIN records of its own, they are also checked against the
    history (their own τ̂ and slow-tail estimate, two-sample, at Z_DETECT; and a slow tail in them
    alone): an instrument that changed under the same key stops the pool vouching, as a mismatch.

    A new instrument's pool may also start from other instruments' records (``prior``: its type's
    or its station's, where the station says they share τ and tail), scaled to count as
    ``prior_records`` records less the instrument's own earlier ones: each record of its own
    replaces one of the prior's, so its own runs overtake the prior and then leave it out. The
    prior joins the history in that check, so an instrument unlike its type stops the pool vouching
    once it has POOL_MIN records of its own. It is never kept in the instrument's state."""

    def __init__(self, tau_guess: float, noise_v: float, history: PoolState | None = None,
                 prior: PoolState | None = None, prior_records: int = 0):
        self.taus = tau_guess * np.geomspace(*TAU_RANGE, TAU_GRID)
        self.noise_v = noise_v
        self.records = 0  # the instrument's own: its earlier runs' and this run's
        self.mismatch = ""  # why the pool stopped vouching for the model, once it has
        # per grid τ: rss, x·x, x·d, d·d, x·r, d·r (x: the slow shape, d: ∂/∂τ, both times a)
        self._sums = np.zeros((6, TAU_GRID))
        self._own = np.zeros((6, TAU_GRID))  # this run's records alone
        self.own_records = 0
        self._prior: PoolState | None = None
        for state in (history, prior):
            if state is not None and state.sums.shape != self._sums.shape:
                raise ValueError(f"a pool's sums are {state.sums.shape}, not {self._sums.shape}")
        if history is not None and history.records:
            self._prior = history
            self._sums, self.records, self.mismatch = history.sums.copy(), history.records, history.mismatch
        # other instruments' records (the type's, the station's), scaled to fill the pool up to
        # prior_records: each of the instrument's own earlier records replaces one of them
        self.lent = 0.0  # how many records the prior counts as
        self._lent = np.zeros((6, TAU_GRID))
        if prior is not None and prior.records and prior_records > self.records:
            self.lent = float(min(prior.records, prior_records - self.records))
            self._lent = prior.sums * (self.lent / prior.records)
            before = self._prior.sums if self._prior is not None else np.zeros_like(self._lent)
            self._prior = PoolState(before + self._lent, round(self.records + self.lent), self.mismatch)

    @property
    def pooled(self) -> float:
        """The records the pool's estimates rest on: the instrument's own and what the prior counts as."""
        return self.records + self.lent

    def _all(self) -> NDArray:
        return self._sums + self._lent

    def state(self) -> PoolState:
        """Everything the pool knows of its own instrument (the prior left out), to be kept for the
        instrument's next run."""
        return PoolState(self._sums.copy(), self.records, self.mismatch)

    def own_state(self) -> PoolState:
        """This run's records alone: what it adds to its type's and station's records."""
        return PoolState(self._own.copy(), self.own_records, self.mismatch)

    def add(self, volts: NDArray, t: NDArray) -> None:
        """One point's record: (n, channels) samples at t seconds after the motion ended."""
        volts = volts[:, ~np.isnan(volts).all(axis=0)]  # a package's absent sensors record nothing
        e = np.exp(-t[None, :] / self.taus[:, None])  # (τ, n)
        channels = np.broadcast_to(volts.T, (TAU_GRID, *volts.T.shape))  # (τ, channel, n)
        amp = _line_fit(channels, e[:, None, :])[1]  # (τ, channel)
        fitted = _project_out(channels, e[:, None, :])  # residuals
        slow = _project_out(np.exp(-t[None, :] / (SLOW * self.taus[:, None])), e)  # (τ, n)
        dtau = _project_out(t[None, :] / self.taus[:, None] ** 2 * e, e)
        a2 = (amp**2).sum(axis=1)
        xr = np.einsum("gn,gkn,gk->g", slow, fitted, amp)
        dr = np.einsum("gn,gkn,gk->g", dtau, fitted, amp)
        record = np.array([(fitted**2).sum(axis=(1, 2)), (slow**2).sum(1) * a2,
                           (slow * dtau).sum(1) * a2, (dtau**2).sum(1) * a2, xr, dr])
        self._sums += record
        self._own += record
        self.records += 1
        self.own_records += 1
        if self.pooled >= POOL_MIN and not self.mismatch:
            tau = self.tau()
            if tau is None:
                self.mismatch = "model: τ outside its search range (pooled)"
            elif abs(z := self.slow_z()) >= Z_DETECT:
                self.mismatch = f"model: a slow tail in the pooled records (z = {z:+.1f})"
            elif self._prior is not None and min(self._prior.records, self.own_records) >= POOL_MIN:
                self.mismatch = self._unlike_history()

    def _unlike_history(self) -> str:
        """Why this run's records are not the earlier runs' instrument (empty when they agree): its
        own τ̂, or its own slow-tail estimate at the pooled τ̂, differs from the history's by
        Z_DETECT of their combined standard errors, or its own records alone see a slow tail."""
        assert self._prior is not None
        own, before = _tau_of(self._own, self.taus, self.noise_v), _tau_of(self._prior.sums, self.taus,
                                                                           self.noise_v)
        if own is None or before is None:
            return "model: τ outside its search range (this run's records)"
        if abs(z := (own[0] - before[0]) / math.hypot(own[1], before[1])) >= Z_DETECT:
            return f"model: this run's τ differs from the earlier runs' (z = {z:+.1f})"
        i = int(np.argmin(self._all()[0]))
        (b_own, se_own), (b_before, se_before) = _slow_of(self._own, i), _slow_of(self._prior.sums, i)
        if abs(z := b_own / (self.noise_v * se_own)) >= Z_DETECT:
            return f"model: a slow tail in this run's records (z = {z:+.1f})"
        z = (b_own - b_before) / (self.noise_v * math.hypot(se_own, se_before))
        if abs(z) >= Z_DETECT:
            return f"model: this run's slow tail differs from the earlier runs' (z = {z:+.1f})"
        return ""

    def tau(self) -> tuple[float, float] | None:
        """(τ̂, its SE) from the pooled sums, or None when the minimum is on the range's edge."""
        return _tau_of(self._all(), self.taus, self.noise_v)

    def _at_tau(self) -> list[float]:
        """x·x, x·d, d·d, x·r, d·r at the grid τ nearest τ̂."""
        sums = self._all()
        return sums[1:, int(np.argmin(sums[0]))].tolist()

    def slow_z(self) -> float:
        """The pooled score for a slow tail, in its standard deviations (0 before POOL_MIN)."""
        if self.pooled < POOL_MIN:
            return 0.0
        xx, xd, dd, xr, dr = self._at_tau()
        return (xr - xd * dr / dd) / (self.noise_v * math.sqrt(max(xx - xd**2 / dd, 1e-300)))

    def slow_seen(self, beta: float) -> float:
        """The pooled z at which a slow tail of β times each record's transient would show."""
        xx, xd, dd, _, _ = self._at_tau()
        return beta * math.sqrt(max(xx - xd**2 / dd, 0.0)) / self.noise_v

    def slow_per_tau(self) -> float:
        """How much a slow tail of unit β moves τ̂ (the pooled fit absorbs part of it)."""
        xx, xd, dd, _, _ = self._at_tau()
        return xd / dd


@dataclass(frozen=True)
class TailFit:
    settled_v: NDArray  # c per channel
    se_v: NDArray  # its standard error: the noise model's, and τ̂'s
    verdict: Verdict
    amplitude_v: NDArray | None = None  # a per channel (None: the pool gave no τ̂ to fit with)


def _shape_criteria(t: NDArray, a: NDArray, pool: TailPool, tau: float, tau_se: float,
                    target: float) -> tuple[NDArray, float]:
    """What a record at times t with transient amplitudes a can promise, noise aside: c's standard
    error (the noise model's and τ̂'s), and the pooled z at which the slow tail that would bias c by
    σ/(3√N) shows (it moves c directly and through the τ̂ it shifts)."""
    e = np.exp(-t / tau)
    design = np.column_stack([np.ones(len(t)), e])
    to_c = np.linalg.solve(design.T @ design, design.T)[0]  # how a record's shape moves c
    d = t / tau**2 * e  # ∂e/∂τ
    se = np.hypot(pool.noise_v * math.sqrt(float(to_c @ to_c)), np.abs(a * (to_c @ d)) * tau_se)
    per_beta = np.abs(a) * abs(float(to_c @ (np.exp(-t / (SLOW * tau)) - pool.slow_per_tau() * d)))
    return se, pool.slow_seen(target / 3 / max(float(per_beta.max()), 1e-300))


def fit_tail(volts: NDArray, t: NDArray, pool: TailPool, samples: int) -> TailFit:
    """Fit c_k + a_k·e^{−t/τ̂} to an (n, channels) record at t seconds after the motion ended, τ̂
    the pool's, and judge it: the pool vouches for the model (no mismatch seen, and its upper
    bound on a slow tail biases this point by at most σ/(3√N)), the residuals are consistent with
    the noise model (χ²), and c's standard error, τ̂'s share included, is at most σ/√N."""
    present = ~np.isnan(volts).all(axis=0)
    if not present.all():  # a package's absent sensors (NaN columns): fitted on the ones it has
        return _spread(fit_tail(volts[:, present], t, pool, samples), present)
    n, k = volts.shape
    target = pool.noise_v / math.sqrt(samples)
    if pool.mismatch:
        return TailFit(volts.mean(axis=0), np.full(k, np.inf), Verdict(False, pool.mismatch))
    if pool.pooled < POOL_MIN or (found := pool.tau()) is None:
        return TailFit(volts.mean(axis=0), np.full(k, np.inf), Verdict(False, "model: τ not pooled yet"))
    tau, tau_se = found
    design = np.column_stack([np.ones(n), np.exp(-t / tau)])
    c, a = np.linalg.lstsq(design, volts, rcond=None)[0]
    resid = volts - design @ np.vstack([c, a])
    se, seen = _shape_criteria(t, a, pool, tau, tau_se, target)
    if float(np.sum(resid**2)) / pool.noise_v**2 > chi2_quantile(0.999, n * k - 2 * k):
        verdict = Verdict(False, "model: residuals above the noise model")
    elif np.any(se > target):
        verdict = Verdict(False, "model: settled value not yet precise enough")
    elif seen < abs(pool.slow_z()) + Z_BOUND:
        verdict = Verdict(False, "model: the pooled records cannot yet rule out a slow tail")
    else:
        verdict = Verdict(True, f"settled (model, pooled τ = {tau:.4g} s)")
    return TailFit(c, se, verdict, a)


def _spread(fit: TailFit, present: NDArray) -> TailFit:
    """A fit of the present channels, NaN in the absent ones' places (as the record had them)."""
    def full(values: NDArray) -> NDArray:
        out = np.full(present.shape, np.nan)
        out[present] = values
        return out

    return TailFit(full(fit.settled_v), full(fit.se_v), fit.verdict,
                   None if fit.amplitude_v is None else full(fit.amplitude_v))


def _samples_needed(t: NDArray, sample_s: float, pool: TailPool, fit: TailFit, samples: int,
                    most: int) -> int:
    """The shortest record (at most ``most`` samples) whose noise-free criteria could pass, given
    the amplitudes fitted so far: where to read to next."""
    found = pool.tau() if fit.amplitude_v is not None else None
    if found is None or fit.amplitude_v is None:
        return most
    target = pool.noise_v / math.sqrt(samples)
    for m in range(len(t) + 1, most + 1):
        longer = np.concatenate([t, t[-1] + sample_s * np.arange(1, m - len(t) + 1)])
        se, seen = _shape_criteria(longer, fit.amplitude_v, pool, *found, target)
        if np.all(se <= target) and seen >= abs(pool.slow_z()) + Z_BOUND:
            return m
    return most


def dwell_model(dmm: Voltmeter, clock: Clock, transient_v: float, settings: SettleSettings,
                motion_end: float | None = None, sample_s: float = 0.0, pool: TailPool | None = None
                ) -> Dwell:
    """Model settling: sample from now (in position) and return the fitted settled value once
    `fit_tail` accepts it; if it has not by the time a conventional window (from the dead time
    after ``motion_end``) would end, the record's last N samples are that window and `dwell` goes
    on from it: a mismatch costs no more than waiting. Either way the record joins ``pool`` (the
    run's; a fresh one when None). The verdict says why it waited."""
    pool = pool if pool is not None else TailPool(settings.tau_s, settings.noise_v)
    t0 = clock.now()
    start = t0 if motion_end is None else min(motion_end, t0)
    n = settings.samples
    t_read = clock.now()
    scan = dmm.read(n)
    sample_s = (clock.now() - t_read) / n
    t = t_read - start + (np.arange(n) + 0.5) * sample_s  # each sample's time since the motion ended
    window_end = start + float(dead_time(transient_v, settings, sample_s)) + n * sample_s
    while True:
        fit = fit_tail(scan.volts, t, pool, n)
        if fit.verdict.settled:
            pool.add(scan.volts, t)
            return Dwell(scan, clock.now() - t0, fit.verdict, sample_s,
                         (fit.settled_v, fit.se_v * math.sqrt(len(t))))
        left_s = window_end - clock.now()
        if left_s <= 1e-9:  # the record's end is a conventional window
            break
        left = max(1, math.floor(left_s / sample_s + 1e-9))
        more = max(1, _samples_needed(t, sample_s, pool, fit, n, len(t) + left) - len(t))
        if more >= left:  # no model verdict before the window's end: end the record on it exactly
            clock.sleep(max(0.0, left_s - left * sample_s))
            more = left
        t_read = clock.now()
        extra = dmm.read(more)
        t = np.concatenate([t, t_read - start + (np.arange(more) + 0.5) * sample_s])
        scan = Scan(np.concatenate([scan.volts, extra.volts]),
                    None if scan.temp_c is None else np.concatenate([scan.temp_c, extra.temp_c]))
    pool.add(scan.volts, t)
    fallback = dwell(dmm, clock, transient_v, settings, motion_end, sample_s,
                     Scan(scan.volts[-n:], None if scan.temp_c is None else scan.temp_c[-n:]))
    why = f"{fallback.verdict.reason} (waited: {fit.verdict.reason})"
    return Dwell(fallback.scan, clock.now() - t0, Verdict(fallback.verdict.settled, why), fallback.sample_s)
