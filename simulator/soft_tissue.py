"""Soft-tissue artefact (STA) for the simulated human: each skin sensor's placement on its bone moves as a
smooth, deterministic function of the angles of the joints at either end of its segment, up to a set
size at the ends of a range and back to the rest placement when the joints come back to rest.

Not noise: the same pose always gives the same placement, which is what makes STA look like a slip
to a monitor that only watches residuals rise, and what a monitor can tell apart from a slip (a step).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np

from flockcal.simulator.body import BodyModel, SimulatorError
from flockcal.rotations import from_rotvec

DEFAULT_STA_MM = 12.0  # the middle of the 10–15 mm real skin sensors show at the ends of a range
# The sensor also tilts as the skin under it stretches: this many radians per metre of slide
# (0.2° per mm, so 2.4° at 12 mm), the order clusters on the thigh show.
TILT_RAD_PER_M = np.radians(0.2) * 1000.0
_GRID = 7  # points per joint axis when finding a joint's largest effect


@dataclass(frozen=True)
class SoftTissue:
    """Sensor placements as a function of the joint coordinates q (n, m, 3) of a `BodyModel`.

    Placement offset and tilt are polynomials of degree two in each neighbouring joint's normalised
    coordinates z = (q − rest) / (the larger of the range's two sides from rest), so |z| ≤ 1 and z = 0
    at rest. For each (sensor, neighbouring joint) the largest slide over that joint's whole range is
    `size_mm` (the sensor's own inboard joint), or `size_mm` shared among its outboard joints; the joints'
    effects add. Built once from the seed; `placements` is two matrix products per batch of frames.
    """

    size_mm: float
    seed: int
    scale: np.ndarray  # (m, 3) 1 / normalising half-range per joint coordinate (0 where no DOF)
    rest: np.ndarray  # (m, 3)
    slide: np.ndarray  # (2·3m, 3m): [z, z²] features → offset change of every sensor, bone frame, metres
    tilt: np.ndarray  # (2·3m, 3m): the same features → rotation vector of every sensor's tilt, bone frame

    @classmethod
    def for_model(cls, model: BodyModel, size_mm: float, seed: int) -> "SoftTissue":
        """One skin sensor per body, at the model's sensor sites (its box's z axis is the skin normal)."""
        normals = [model.sensor_rotation[i][:, 2] for i in range(model.m)]
        return cls.for_sites(model, np.arange(model.m), np.array(normals), size_mm, seed)

    @classmethod
    def for_sites(cls, model: BodyModel, body: np.ndarray, normal: np.ndarray, size_mm: float, seed: int,
                  stream: int = 0x57A) -> "SoftTissue":
        """Skin sites (sensors or markers) `body` (s,) on the model's bodies, each with its skin `normal`
        (s, 3) in the bone frame; every site gets its own slide by the rule above (`stream` keeps the
        sensor path's draws when markers are added)."""
        if not 0.0 <= float(size_mm) <= 50.0:
            raise SimulatorError(f"soft-tissue artefact of {size_mm} mm is outside 0–50 mm; real skin moves 5–15 mm")
        m, sites = model.m, len(body)
        rng = np.random.default_rng([int(seed), stream])
        lo, hi, rest = model.limits[..., 0], model.limits[..., 1], model.rest
        half = np.maximum(hi - rest, rest - lo)
        dofs = np.array([model.dofs(i) for i in range(m)])
        used = np.arange(3)[None, :] < dofs[:, None]
        scale = np.where(used & (half > 0), 1.0 / np.where(half > 0, half, 1.0), 0.0)
        slide = np.zeros((2, m, 3, sites, 3))  # (feature kind, joint, dof, site, xyz)
        tilt = np.zeros((2, m, 3, sites, 3))
        for s_, i in enumerate(np.asarray(body, dtype=int)):
            normal_s = np.asarray(normal[s_], dtype=float)
            inboard = [i] if dofs[i] else []
            outboard = [k for k in model.children(i) if dofs[k]]
            shares = [(k, 1.0) for k in inboard] + [(k, 1.0 / len(outboard)) for k in outboard]
            for k, share in shares:
                d = int(dofs[k])
                # Mostly along the skin, a little into or out of it (the muscle under it bulges).
                vec = rng.normal(size=(2, d, 3))
                vec -= 0.7 * np.einsum("...j,j->...", vec, normal_s)[..., None] * normal_s
                vec *= rng.uniform(0.3, 1.0, size=(2, d, 1))  # linear and quadratic parts, per axis
                rot = rng.normal(size=(2, d, 3)) * rng.uniform(0.3, 1.0, size=(2, d, 1))
                z_lo = np.where(scale[k, :d] > 0, (lo[k, :d] - rest[k, :d]) * scale[k, :d], 0.0)
                z_hi = np.where(scale[k, :d] > 0, (hi[k, :d] - rest[k, :d]) * scale[k, :d], 0.0)
                grid = np.array(list(product(*[np.linspace(a, b, _GRID) for a, b in zip(z_lo, z_hi)])))
                F = np.concatenate([grid, grid**2], axis=1)  # (g, 2d)
                peak_slide = np.linalg.norm(F @ vec.reshape(2 * d, 3), axis=1).max()
                peak_tilt = np.linalg.norm(F @ rot.reshape(2 * d, 3), axis=1).max()
                slide[:, k, :d, s_] = vec * (share * size_mm * 1e-3 / max(peak_slide, 1e-12))
                tilt[:, k, :d, s_] = rot * (share * size_mm * 1e-3 * TILT_RAD_PER_M / max(peak_tilt, 1e-12))
        return cls(float(size_mm), int(seed), scale, rest.copy(),
                   slide.reshape(6 * m, 3 * sites), tilt.reshape(6 * m, 3 * sites))

    def features(self, q: np.ndarray) -> np.ndarray:
        """[z, z²] (n, 2·3m) of joint coordinates q (n, m, 3), z clipped to the range."""
        z = np.clip((q - self.rest) * self.scale, -1.0, 1.0).reshape(len(q), -1)
        return np.concatenate([z, z * z], axis=1)

    def slides(self, q: np.ndarray, F: np.ndarray | None = None) -> np.ndarray:
        """Each sensor's offset from its rest placement (n, m, 3) at coordinates q, bone frame, metres."""
        F = self.features(q) if F is None else F
        return (F @ self.slide).reshape(len(F), -1, 3)

    def tilts(self, q: np.ndarray, F: np.ndarray | None = None) -> np.ndarray:
        """Each sensor's tilt from its rest axes (n, m, 3, 3), as a rotation in the bone frame."""
        F = self.features(q) if F is None else F
        return from_rotvec((F @ self.tilt).reshape(len(F), -1, 3))

    def placements(self, q: np.ndarray, offsets: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every sensor's rotation (n, m, 3, 3) and offset (n, m, 3) in its bone frame at coordinates q,
        from the rest placements `rotations` (m, 3, 3) and `offsets` (m, 3)."""
        F = self.features(q)
        return self.tilts(q, F) @ rotations, offsets[None] + self.slides(q, F)

    def describe(self) -> dict:
        """What the truth file records: enough to rebuild the same artefact (size, seed, the rule)."""
        return {"size_mm": self.size_mm, "seed": self.seed,
                "tilt_deg_per_mm": float(np.degrees(TILT_RAD_PER_M) / 1000.0),
                "rule": "placement = rest + quadratic in each neighbouring joint's normalised angles; "
                        "largest slide per joint = size_mm (inboard) or size_mm shared (outboard joints)"}
