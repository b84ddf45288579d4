"""A sensor after the tables stop, as it might really be rather than as model settling assumes:
to validate `labcal.run.settle.dwell_model` against what it was not built from.

The output of channel k at t seconds after the motion ends is

    settled_k + Δv_k·Σ_j w_j·e^{−t/τ_j}  + white noise (σ per sample) + 1/f noise,

with Σ_j w_j = 1 (one pole: the model's own shape; two poles: a second, slower or faster, lag
in the sensor or its filter). Each sample is the DMM's integration over its aperture: the mean of
the exponential over [t, t + dt] is written out in closed form (τ/dt·(e^{−t/τ} − e^{−(t+dt)/τ})),
not taken from labcal. The 1/f noise is white noise shaped by 1/√f in the frequency domain over a
record of ``record_s`` (drawn once per sensor: a slow wander that stays correlated across the
record), scaled to ``pink_v`` rms per sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from labcal.devices.station import Scan
from labcal.sim.clock import VirtualClock


@dataclass
class TailSensor:
    clock: VirtualClock
    settled_v: np.ndarray  # (channels,)
    step_v: np.ndarray  # Δv per channel: the transient at motion end
    poles: tuple[tuple[float, float], ...]  # (weight, τ s), weights summing to 1
    sample_s: float
    noise_v: float
    rng: np.random.Generator
    pink_v: float = 0.0
    record_s: float = 60.0
    measures_temperature: bool = False
    _pink: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = int(np.ceil(self.record_s / self.sample_s)) + 1
        k = len(self.settled_v)
        if self.pink_v > 0:
            freq = np.fft.rfftfreq(n)
            shape = np.where(freq > 0, 1 / np.sqrt(np.where(freq > 0, freq, 1.0)), 0.0)
            white = self.rng.normal(size=(2, k, len(freq)))
            spectrum = (white[0] + 1j * white[1]) * shape
            pink = np.fft.irfft(spectrum, n=n, axis=1).T
            self._pink = pink / pink.std() * self.pink_v
        else:
            self._pink = np.zeros((n, k))

    def transient(self, t: np.ndarray) -> np.ndarray:
        """Mean over each aperture [t, t + dt] of Σ w_j·e^{−t/τ_j} (per unit step)."""
        dt = self.sample_s
        return np.sum([w * tau / dt * (np.exp(-t / tau) - np.exp(-(t + dt) / tau)) for w, tau in self.poles],
                      axis=0)

    def read(self, n_samples: int) -> Scan:
        start = self.clock.now()
        t = start + self.sample_s * np.arange(n_samples)
        index = np.minimum((t / self.sample_s).astype(int), len(self._pink) - 1)
        volts = (self.settled_v + np.outer(self.transient(t), self.step_v) + self._pink[index]
                 + self.rng.normal(0.0, self.noise_v, (n_samples, len(self.settled_v))))
        self.clock.sleep(n_samples * self.sample_s)
        return Scan(volts)
