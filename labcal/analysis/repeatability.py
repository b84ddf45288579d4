"""The instrument's own repeatability, from the scatter of the samples inside each calibration window.

A reading of the instrument in use is the mean of N samples of its outputs at one attitude. What
scatters it is the instrument's (and its voltmeter's) noise, σ per sample, so σ/√N for the mean (GUM
4.2.3: the experimental standard deviation of the mean). The calibration measures σ directly: every
point is a window of n_i samples taken while the tables stand still, and the scatter inside a window
owes nothing to where the tables point — the tables' index and wobble errors, a remount, a
nonlinearity, a drift over the run all move a window's samples together. Pooled over the windows
(GUM 4.2.4, H.3.6: s² = Σ(n_i − 1)s_i² / Σ(n_i − 1), with ν = Σ(n_i − 1) degrees of freedom), it is
the Type A evaluation of σ with the run's many degrees of freedom.

The calibration's residual standard error is not this: at the bench it also holds the tables'
per-angle errors, which a reading in use does not have (the instrument is no longer on the tables;
JCGM 100 F.1.1.2 asks for the variability of the measurement as made, here the reading in use) and
which reach the coefficients, and through them every later reading, as the budget's Type B table rows.

The samples inside a window are taken as independent (white noise at the DMM's sample rate). A
correlated noise (a 1/f floor, a slow wander within the window) would make the pooled within-window
scatter understate the scatter of window means; the lack-of-fit test (`labcal.analysis.lack_of_fit`)
compares the residuals with what this σ and the stated table errors predict, so such noise shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.readings import Readings


@dataclass(frozen=True)
class Repeatability:
    """Pooled within-window standard deviation of one sample per channel, with its degrees of
    freedom, the number of windows it pools and the calibration's window length (samples)."""

    sample_sd: NDArray[np.float64]  # (3,)
    dof: float
    windows: int
    window_samples: int  # the calibration's averaging: the most frequent window length

    def reading_variance(self, samples: int) -> NDArray[np.float64]:
        """Variance of one reading in use averaged over ``samples`` samples: s²/N (GUM 4.2.3)."""
        return np.asarray(self.sample_sd**2 / samples, dtype=float)


def repeatability(readings: Readings) -> Repeatability | None:
    """The readings' pooled within-window scatter; None where the readings do not carry their windows'
    scatter (or no window has two samples, or every window is noise-free)."""
    if readings.window_sd is None or readings.window_n is None:
        return None
    n = np.asarray(readings.window_n, dtype=float)
    sd = np.asarray(readings.window_sd, dtype=float)
    ok = (n >= 2) & np.all(np.isfinite(sd), axis=1)
    dof = float(np.sum(n[ok] - 1))
    if dof <= 0:
        return None
    pooled = np.sqrt(np.sum((n[ok] - 1)[:, None] * sd[ok] ** 2, axis=0) / dof)
    if not np.all(pooled > 0):
        return None
    lengths, counts = np.unique(n[ok].astype(int), return_counts=True)
    return Repeatability(pooled, dof, int(ok.sum()), int(lengths[np.argmax(counts)]))
