"""Motion routines for a simulated body: smooth, seeded functions of continuous time.

Each routine ("exercise", "walk", "kiosk", "idle") is a loop of `period` seconds built from sinusoids
with a whole number of cycles per loop and C² envelopes, so it can be evaluated at any times (the live
fake tracker streams forever) and every joint stays inside its limits by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from flockcal.simulator.body import BodyModel, SimulatorError, segment
from flockcal.rotations import axis_angle, rot_z, from_rotvec

ROUTINES = ("exercise", "walk", "kiosk", "idle")
_CHUNK = 20000  # frames evaluated at once, so a long stream never builds huge temporaries


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Quintic 0→1 ramp on [0, 1] with zero first and second derivatives at both ends (C²)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def plateau(u: np.ndarray, ramp: float = 0.2) -> np.ndarray:
    """C² window on u ∈ [0, 1]: ramps up over `ramp`, holds 1, ramps down; zero outside [0, 1]."""
    inside = (u > 0.0) & (u < 1.0)
    w = smoothstep(u / ramp) * smoothstep((1.0 - u) / ramp)
    return np.where(inside, w, 0.0)


@dataclass
class Motion:
    """A routine for one model: joint coordinates and root pose as smooth functions of time.

    Evaluate anywhere with `at(times)`; `times`, `local_rotations` and `root_translation` hold the
    sampled take (seconds × rate_hz frames). Coordinates q (n, m, 3) follow BodyModel.limits.
    """

    model: BodyModel
    name: str
    seconds: float
    rate_hz: float
    seed: int
    period: float
    params: dict = field(repr=False)

    @cached_property
    def times(self) -> np.ndarray:
        return np.arange(int(round(self.seconds * self.rate_hz))) / self.rate_hz

    @cached_property
    def _sampled(self):
        return self.at(self.times)

    @property
    def local_rotations(self) -> np.ndarray:
        return self._sampled[0]

    @property
    def root_translation(self) -> np.ndarray:
        return self._sampled[1]

    def coordinates(self, times) -> np.ndarray:
        """Joint coordinates q (n, m, 3): rotation vectors for ball joints, angle in [..., 0] for hinges."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        if len(t) > _CHUNK:
            return np.concatenate([self.coordinates(t[k : k + _CHUNK]) for k in range(0, len(t), _CHUNK)])
        p = self.params
        ph = 2.0 * np.pi * t[:, None, None, None] / self.period  # (n,1,1,1)
        fast = np.sum(p["fast_a"] * np.sin(ph * p["fast_n"] + p["fast_phi"]), axis=-1)  # (n,m,3)
        slow = np.sum(p["slow_a"] * np.sin(ph * p["slow_n"] + p["slow_phi"]), axis=-1)
        W = p["w0"] + p["w1"] * self._envelope(t)[:, :, None]
        if p["finale_len"] > 0:
            u = ((t % self.period) - p["finale_start"]) / p["finale_len"]
            W = W + p["w2"] * plateau(u)[:, None, None]
        lo, hi, rest = self.model.limits[..., 0], self.model.limits[..., 1], self.model.rest
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        target_fast = mid + half * fast
        target_slow = mid + half * slow
        # A convex mix of rest, fast and slow targets, each inside the limits: so is the result.
        return rest + W * (target_fast - rest) + (1.0 - W) * p["eps"] * (target_slow - rest)

    def _envelope(self, t: np.ndarray) -> np.ndarray:
        """Per-joint activity window (n, m) in [0, 1]; zero for routines without a schedule."""
        p = self.params
        u = ((t[:, None] % self.period) - p["slot_start"]) / p["slot_len"]
        return plateau(u, ramp=0.2)

    def root_pose(self, times) -> tuple[np.ndarray, np.ndarray]:
        """Root rotation (n, 3, 3) and position (n, 3) in the transmitter frame."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        r = self.params["root"]
        w = 2.0 * np.pi * t / self.period
        offset = np.sum(r["pos_a"] * np.sin(w[:, None, None] * r["pos_n"] + r["pos_phi"]), axis=-1)  # (n,3)
        tilt = np.sum(r["tilt_a"] * np.sin(w[:, None, None] * r["tilt_n"] + r["tilt_phi"]), axis=-1)
        yaw = np.sum(r["yaw_a"] * np.sin(w[:, None] * r["yaw_n"] + r["yaw_phi"]), axis=-1)
        heading = self.model.home_rotation
        if r.get("loop_n", 0):
            # Walk a closed ellipse, facing along the path.
            phi = w * r["loop_n"]
            a, b = r["loop_axes"]
            cx = r["loop_centre"]
            offset = offset + np.column_stack([cx + a * np.cos(phi), b * np.sin(phi), np.zeros_like(phi)])
            heading_angle = np.arctan2(b * np.cos(phi), -a * np.sin(phi))
            heading = rot_z(heading_angle)
        Rroot = rot_z(yaw) @ heading @ from_rotvec(tilt)
        return Rroot, self.model.home_position + offset

    def at(self, times) -> tuple[np.ndarray, np.ndarray]:
        """(local_rotations (n, m, 3, 3), root_translation (n, 3)) at any times, in seconds."""
        return self.pose(times)[:2]

    def pose(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`at(times)` and the joint coordinates q (n, m, 3) it came from (soft tissue follows them)."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        q = self.coordinates(t)
        model = self.model
        L = np.empty(q.shape[:2] + (3, 3))
        types = np.array(model.joint_type)
        ball, hinge = types == "ball", types == "hinge"
        if ball.any():
            L[:, ball] = from_rotvec(q[:, ball])
        if hinge.any():
            L[:, hinge] = axis_angle(model.hinge_axis[hinge][None], q[:, hinge, 0])
        L[:, (types == "rigid") | (types == "root")] = np.eye(3)
        Rroot, root_t = self.root_pose(t)
        L[:, model.root] = Rroot
        return L, root_t, q


def routine(
    model: BodyModel,
    name: str = "walk",
    seconds: float = 45.0,
    rate_hz: float = 100.0,
    seed: int = 0,
    period: float | None = None,
) -> Motion:
    """A seeded motion routine for `model`: "exercise", "walk", "kiosk" or "idle".

    The routine loops every `period` seconds (default: exercise = the take length, at least 2 s per
    joint; kiosk 30 s; walk and idle 60 s); `seconds` and `rate_hz` (1–144 Hz) set the sampled take.
    """
    if name not in ROUTINES:
        raise SimulatorError(f"unknown motion {name!r}; choose one of {', '.join(ROUTINES)}")
    if not 1.0 <= float(rate_hz) <= 144.0:
        raise SimulatorError(f"rate {rate_hz} Hz is outside the tracker's 1–144 Hz")
    if not 0.0 < float(seconds) <= 24 * 3600:
        raise SimulatorError(f"seconds must be positive (up to a day), not {seconds}")
    joints = [i for i in range(model.m) if model.dofs(i) > 0]
    if period is None:
        period = {
            "exercise": max(float(seconds), 2.0 * max(len(joints), 1)),
            "kiosk": 30.0,
            "walk": 60.0,
            "idle": 60.0,
        }[name]
    period = float(period)
    if period <= 0:
        raise SimulatorError(f"period must be positive, not {period}")
    rng = np.random.default_rng([int(seed), ROUTINES.index(name), 0x3071])
    builder = {"exercise": _exercise, "walk": _walk, "kiosk": _kiosk, "idle": _idle}[name]
    params = builder(model, joints, period, rng)
    params["root"] = _root(model, name, period, rng)
    return Motion(model, name, float(seconds), float(rate_hz), int(seed), period, params)


# ----------------------------------------------------------------------------------------------
# Parameter builders. Every sinusoid has a whole number of cycles per period, so loops are seamless.


def _cycles(freq_hz, period: float) -> np.ndarray:
    return np.maximum(1.0, np.round(np.asarray(freq_hz) * period))


def _base(model: BodyModel, period: float, rng: np.random.Generator, k: int = 3) -> dict:
    """Zero-amplitude parameters with a random slow background (0.05–0.3 Hz) on every DOF."""
    m = model.m
    slow_a = rng.dirichlet(np.ones(k), size=(m, 3)) * 0.9
    return {
        "fast_a": np.zeros((m, 3, k)),
        "fast_n": np.ones((m, 3, k)),
        "fast_phi": np.zeros((m, 3, k)),
        "slow_a": slow_a,
        "slow_n": _cycles(rng.uniform(0.05, 0.3, (m, 3, k)), period),
        "slow_phi": rng.uniform(0, 2 * np.pi, (m, 3, k)),
        "w0": np.zeros((m, 3)),
        "w1": np.zeros((m, 3)),
        "eps": np.zeros((m, 3)),
        "slot_start": np.zeros(m),
        "slot_len": np.full(m, np.inf),
        "w2": np.zeros((m, 3)),
        "finale_start": 0.0,
        "finale_len": 0.0,
    }


def _sweep(p: dict, i: int, rng: np.random.Generator, period: float, lo_hz: float, hi_hz: float) -> None:
    """One full-range sinusoid per DOF of joint i, at distinct frequencies so the axes decorrelate."""
    freqs = np.sort(rng.uniform(lo_hz, hi_hz, 3)) * np.array([1.0, 1.31, 0.77])
    p["fast_a"][i] = 0.0
    p["fast_a"][i, :, 0] = 0.97
    p["fast_n"][i, :, 0] = _cycles(freqs, period)
    p["fast_phi"][i, :, 0] = rng.uniform(0, 2 * np.pi, 3)


def _exercise(model: BodyModel, joints: list[int], period: float, rng: np.random.Generator) -> dict:
    """Each joint in turn sweeps its whole range on every axis while the rest barely move."""
    p = _base(model, period, rng)
    slots = _disjoint_slots(model, joints)
    slot = period / max(len(slots), 1)
    # At least ~1.5 sweeps per slot, so a routine squeezed into a short loop still turns every joint
    # through its range (relaxed 0.35–0.6 Hz when there is time, up to 2.5 Hz when there is not).
    lo_hz, hi_hz = min(max(0.35, 1.5 / slot), 2.0), min(max(0.6, 2.5 / slot), 2.5)
    for k, group in enumerate(slots):
        for i in group:
            _sweep(p, i, rng, period, lo_hz, hi_hz)
            p["w1"][i] = 1.0
            p["eps"][i] = 0.06
            p["slot_start"][i] = k * slot
            p["slot_len"][i] = slot
    return p


def _disjoint_slots(model: BodyModel, joints: list[int], per_slot: int = 4) -> list[list[int]]:
    """Group joints that share no body (a left arm joint with a right leg joint, say), so each joint
    still moves alone relative to both its bodies while the take spends more time per joint."""
    slots: list[list[int]] = []
    used: list[set[int]] = []
    for i in joints:
        bodies = {i, int(model.parent[i])}
        for group, taken in zip(slots, used):
            if len(group) < per_slot and not bodies & taken:
                group.append(i)
                taken |= bodies
                break
        else:
            slots.append([i])
            used.append(set(bodies))
    return slots


def _idle(model: BodyModel, joints: list[int], period: float, rng: np.random.Generator) -> dict:
    """Standing still: a slow sway of a few hundredths of each range."""
    p = _base(model, period, rng)
    p["eps"][joints] = 0.035
    return p


def _walk(model: BodyModel, joints: list[int], period: float, rng: np.random.Generator) -> dict:
    """Exaggerated walking: every DOF moves at once, legs and arms phase-locked to the stride."""
    p = _base(model, period, rng)
    stride_hz = rng.uniform(0.8, 0.95)
    stride = _cycles(stride_hz, period)
    for i in joints:
        name, seg = model.names[i], segment(model.names[i])
        side = np.pi if name.startswith("r_") else 0.0
        a = rng.dirichlet([4.0, 1.5, 1.5], size=3) * 0.97  # stride, double-stride, wander
        p["fast_a"][i] = a
        p["fast_n"][i] = np.column_stack([np.full(3, stride), np.full(3, 2 * stride), _cycles(rng.uniform(0.1, 0.4, 3), period)])
        p["fast_phi"][i] = rng.uniform(0, 2 * np.pi, (3, 3))
        p["w0"][i] = 0.55
        if model.kind == "human":
            # Sagittal swing: legs opposite each other, each arm opposite its own leg.
            lead = {"thigh": 0.0, "shin": -np.pi / 2, "foot": np.pi / 2, "upper_arm": np.pi, "forearm": np.pi}.get(seg)
            if lead is not None:
                axis = 0 if model.joint_type[i] == "hinge" else 1
                p["fast_a"][i, axis] = [0.8, 0.15, 0.02]
                p["fast_phi"][i, axis, 0] = lead + side
                p["w0"][i, axis] = 0.9
    p["eps"][joints] = 0.5
    return p


# Whole chains move in their slot, and the slowest come first. A hand left still while its arm swings rides
# rigidly on the forearm, so the fitted tree first hangs it from the upper arm and re-links it once the wrist
# moves (a joint counted done and then taken back); a leg or the trunk turns less than an arm and takes the
# longest to pin, so the guest does it while fresh and the arms, pinned within a second, come last.
_KIOSK_GROUPS = (
    ("l_thigh", "l_shin", "l_foot"),
    ("r_thigh", "r_shin", "r_foot"),
    ("abdomen", "chest", "head"),
    ("upper_arm", "forearm", "hand"),
)


def _kiosk(model: BodyModel, joints: list[int], period: float, rng: np.random.Generator) -> dict:
    """A guest's half-minute routine: each leg, the trunk and head, both arms, then everything gently."""
    p = _base(model, period, rng)
    if model.kind == "human":
        groups = []
        for g in _KIOSK_GROUPS:
            groups.append([i for i in joints if segment(model.names[i]) in g or model.names[i] in g])
    else:
        groups = [list(c) for c in np.array_split(joints, min(5, len(joints)))]
    groups = [g for g in groups if g]
    slot = period / (len(groups) + 1)
    for k, g in enumerate(groups):
        for i in g:
            _sweep(p, i, rng, period, 0.45, 0.8)
            p["w1"][i] = 1.0
            p["slot_start"][i] = k * slot
            p["slot_len"][i] = slot
    # The last slot: everything moves at a third of the range at once, like a short dance.
    p["eps"][joints] = 0.06
    p["w2"][joints] = 0.35
    p["finale_start"], p["finale_len"] = len(groups) * slot, slot
    return p


def _root(model: BodyModel, name: str, period: float, rng: np.random.Generator) -> dict:
    """Root sway/translation/turning amplitudes for the routine; rigs are handled like objects."""
    k = 3
    carried = model.kind != "human"
    amp = {
        # (position m per axis, tilt rad per axis, yaw rad)
        "idle": (0.01, 0.01, 0.02),
        "exercise": (0.04, 0.05, 0.3),
        "kiosk": (0.06, 0.06, 0.4),
        "walk": (0.02, 0.06, 0.0),
    }[name]
    pos_amp, tilt_amp, yaw_amp = amp
    if carried and name != "idle":
        pos_amp, tilt_amp, yaw_amp = 0.1, 0.5, 0.9
    hz = (0.1, 0.3) if name != "walk" else (0.8, 1.9)
    r = {
        "pos_a": rng.dirichlet(np.ones(k), size=3) * pos_amp,
        "pos_n": _cycles(rng.uniform(*hz, (3, k)), period),
        "pos_phi": rng.uniform(0, 2 * np.pi, (3, k)),
        "tilt_a": rng.dirichlet(np.ones(k), size=3) * tilt_amp,
        "tilt_n": _cycles(rng.uniform(*hz, (3, k)), period),
        "tilt_phi": rng.uniform(0, 2 * np.pi, (3, k)),
        "yaw_a": rng.dirichlet(np.ones(k)) * yaw_amp,
        "yaw_n": _cycles(rng.uniform(0.02, 0.1, k), period),
        "yaw_phi": rng.uniform(0, 2 * np.pi, k),
    }
    if name == "walk" and not carried:
        r["loop_n"] = float(_cycles(1.0 / 15.0, period))
        r["loop_axes"] = (0.12, 0.3)
        r["loop_centre"] = 0.25  # further out than standing, so arms swung ahead stay at x > 0
    return r
