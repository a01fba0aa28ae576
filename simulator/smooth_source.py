"""A small deterministic pose source for driver and fake-tracker tests: sensors on slow orbits.
"""

from __future__ import annotations

import numpy as np

from flockcal.rotations import from_euler


class SmoothSource:
    """A small deterministic pose source: m sensors on slow independent orbits inside 0.8 m."""

    def __init__(self, n_sensors: int = 4, seed: int = 0, radius: float = 0.5) -> None:
        rng = np.random.default_rng(seed)
        self.n_sensors = n_sensors
        self.names = tuple(f"s{i}" for i in range(n_sensors))
        self._centre = rng.uniform(-0.2, 0.2, (n_sensors, 3)) + [0.3, 0.0, 0.0]
        self._amp = rng.uniform(0.05, radius - 0.2, (n_sensors, 3))
        self._freq = rng.uniform(0.2, 1.0, (n_sensors, 3))
        self._phase = rng.uniform(0, 2 * np.pi, (n_sensors, 3))
        self._wfreq = rng.uniform(0.1, 0.8, (n_sensors, 3))
        self._valid_until = np.full(n_sensors, np.inf)

    def poses(self, times: np.ndarray):
        t = np.asarray(times, dtype=float)[:, None, None]
        pos = self._centre + self._amp * np.sin(2 * np.pi * self._freq * t + self._phase)
        ang = 3.0 * np.sin(2 * np.pi * self._wfreq * t + self._phase)  # sweeps every Euler range
        rot = from_euler(ang[..., 0], ang[..., 1] / 2.0, ang[..., 2])
        valid = np.broadcast_to(t[:, :, 0] < self._valid_until, pos.shape[:2]).copy()
        return rot, pos, valid

    def invalidate(self, sensor: int, after: float = -np.inf) -> None:
        """Sensor `sensor` gives no valid data from time `after` on (tests of the zero record)."""
        self._valid_until[sensor] = after
