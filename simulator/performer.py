"""A live simulated performer: sensor poses at any times, with faults that can be injected while running.

This is the pose source the fake tracker streams and `take.simulate` records. Poses are a pure
function of the times asked for (and of the faults injected so far), in SI units and the transmitter
frame (+X forward, +Y right, +Z down). Thread-safe: one thread may stream while another injects.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace

import numpy as np

from flockcal.rotations import rot_z
from flockcal.simulator import faults
from flockcal.simulator.body import BodyModel, SimulatorError, bone_poses, by_name
from flockcal.simulator.motion import ROUTINES, Motion, routine as make_routine
from flockcal.simulator.soft_tissue import DEFAULT_STA_MM, SoftTissue

NOISE_KINDS = ("tracker", None)
_VELOCITY_STEP_S = 1e-3


@dataclass(frozen=True)
class SlipEvent:
    """A sensor sliding on its bone at `time_s`: its origin moves by `displacement_m` in the bone frame
    and it turns by `angle_rad` about the skin normal."""

    time_s: float
    sensor: int
    displacement_m: np.ndarray  # (3,), bone frame
    angle_rad: float = 0.0

    def as_dict(self, names) -> dict:
        return {
            "time_s": float(self.time_s),
            "sensor": names[self.sensor],
            "jump_mm": float(np.linalg.norm(self.displacement_m) * 1000.0),
            "angle_deg": float(np.degrees(self.angle_rad)),
            "displacement_bone_m": self.displacement_m.tolist(),
        }


@dataclass(frozen=True)
class _Faults:
    """The injected-fault state, swapped as a whole under the lock so a reader sees one consistent set."""

    slips: tuple[SlipEvent, ...] = ()
    dropout: float = 0.0
    dropout_burst_s: float = 0.0
    unit_scale: float = 1.0
    noise: str | None = "tracker"
    noise_scale: float = 1.0
    hemisphere: str | None = None
    quantise_in: float | None = None
    orientation: str = "matrix"


class Performer:
    """A performer wearing one sensor per body, moving through a looping routine.

    model: "human" | "linkage" | "pair" or a BodyModel; birds: how many sensors (a connected subset);
    routine: "exercise" | "walk" | "kiosk" | "idle"; period: the routine's loop length in seconds
    (default per routine; `seconds` is the take length the routine is planned for, which sets the
    exercise loop);
    noise: "tracker" or None (exact). sta_mm: soft-tissue artefact, the largest slide of a skin
    sensor as a neighbouring joint reaches the end of its range (default 12 mm for a human, 0 = off;
    the rigs have no skin). `full_scale_in` is the position scale the performer needs:
    72 inches (the 36-inch scale clips reaching and walking); a fake tracker should report that.
    """

    full_scale_in = 72.0

    def __init__(
        self,
        model: str | BodyModel = "human",
        routine: str = "walk",
        seed: int = 0,
        noise: str | None = "tracker",
        rate_hz: float = 100.0,
        birds: int | None = None,
        period: float | None = None,
        height: float = 1.75,
        seconds: float = 60.0,
        sta_mm: float | None = None,
    ):
        if noise not in NOISE_KINDS:
            raise SimulatorError(f"unknown noise {noise!r}; choose 'tracker' or None")
        self.model: BodyModel = by_name(model, seed=seed, birds=birds, height=height)
        human = self.model.kind == "human"
        if sta_mm is None:
            sta_mm = DEFAULT_STA_MM if human else 0.0
        if float(sta_mm) > 0 and not human:
            raise SimulatorError(f"the {self.model.kind} has no skin: soft-tissue artefact is for the human "
                                 "model only (leave sta_mm unset or 0)")
        # Skin moving over bone, a smooth function of the joint angles (not noise: see soft_tissue).
        self.sta: SoftTissue | None = SoftTissue.for_model(self.model, sta_mm, seed) if float(sta_mm) > 0 else None
        # Replaced only under _lock (set_routine); a batch of poses reads it once, so it follows one routine.
        self.motion: Motion = make_routine(self.model, routine, seconds, rate_hz, seed, period=period)
        self.seed = int(seed)
        self.rate_hz = float(rate_hz)
        self._lock = threading.Lock()
        self._faults = _Faults(noise=noise)
        self._last_time = 0.0

    # -- what a tracker sees --------------------------------------------------------------------

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    @property
    def n_sensors(self) -> int:
        return self.model.m

    def index(self, sensor: str | int) -> int:
        if isinstance(sensor, (int, np.integer)):
            if not 0 <= int(sensor) < self.n_sensors:
                raise SimulatorError(f"sensor index {sensor} is outside 0..{self.n_sensors - 1}")
            return int(sensor)
        return self.model.index(sensor)

    def exact_poses(self, times) -> tuple[np.ndarray, np.ndarray]:
        """Sensor poses (rotations (n,m,3,3), positions (n,m,3)) with slips but without any tracker error."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        with self._lock:
            state, motion = self._faults, self.motion
        return self._slipped(t, *self._exact(motion, t), state.slips)

    def poses(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotations (n,m,3,3), positions (n,m,3) metres, valid (n,m)) as the tracker reports them.

        Deterministic for given times and injected faults: slips, unit scale, noise, hemisphere
        mirroring (if set), quantisation (if set) and dropouts are applied in that order.
        """
        t = np.atleast_1d(np.asarray(times, dtype=float))
        n = len(t)
        with self._lock:
            state, motion = self._faults, self.motion
            if n:
                self._last_time = max(self._last_time, float(t.max()))
        noisy = state.noise == "tracker" and state.noise_scale > 0
        if noisy:
            # One pass for the frames and their neighbours ±h: the dynamic error needs each sensor's
            # speed, taken by central differences of the smooth motion (slips are steps, not motion).
            h = _VELOCITY_STEP_S
            R, p3 = self._exact(motion, np.concatenate([t, t - h, t + h]), rotated=n)
            p = p3[:n]
            vel = (p3[2 * n :] - p3[n : 2 * n]) * (state.unit_scale / (2 * h))
        else:
            R, p = self._exact(motion, t)
        R, p = self._slipped(t, R, p, state.slips)
        if state.unit_scale != 1.0:
            p = faults.unit_scale(p, state.unit_scale)
        if noisy:
            R, p = faults.tracker_noise(R, p, t, seed=self.seed, velocities=vel, scale=state.noise_scale)
        if state.hemisphere is not None:
            p = faults.hemisphere_flips(p, state.hemisphere)
        valid = np.ones(p.shape[:2], dtype=bool)
        if state.quantise_in is not None:
            R, p, in_range = faults.quantise(R, p, state.quantise_in, state.orientation)
            valid &= in_range
        if state.dropout > 0:
            valid = faults.dropouts(valid, t, state.dropout, seed=self.seed, burst_s=state.dropout_burst_s)
        return R, p, valid

    @property
    def clock_s(self) -> float:
        """The latest time poses were computed for: the performer's clock as a stream sees it."""
        with self._lock:
            return self._last_time

    @property
    def sta_mm(self) -> float:
        return 0.0 if self.sta is None else self.sta.size_mm

    def _exact(self, motion: Motion, t: np.ndarray, rotated: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Exact sensor rotations of the first `rotated` frames (default all) and positions of all."""
        k = len(t) if rotated is None else rotated
        S0, s0 = self.model.sensor_rotation, self.model.sensor_offset
        if self.sta is None:
            L, root = motion.at(t)
            B, b = bone_poses(self.model, L, root)
            return B[:k] @ S0, b + np.einsum("nmij,mj->nmi", B, s0)
        L, root, q = motion.pose(t)
        B, b = bone_poses(self.model, L, root)
        F = self.sta.features(q)
        s = s0[None] + self.sta.slides(q, F)
        return B[:k] @ (self.sta.tilts(q[:k], F[:k]) @ S0), b + np.einsum("nmij,nmj->nmi", B, s)

    def soft_tissue(self, times) -> np.ndarray:
        """How far (n, m) each sensor's placement is from its rest placement at these times, metres."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        if self.sta is None:
            return np.zeros((len(t), self.n_sensors))
        with self._lock:
            motion = self.motion
        return np.linalg.norm(self.sta.slides(motion.coordinates(t)), axis=-1)

    def _slipped(self, t, R, p, slips: tuple[SlipEvent, ...]) -> tuple[np.ndarray, np.ndarray]:
        S = self.model.sensor_rotation.copy()
        for ev in sorted(slips, key=lambda e: e.time_s):
            i = ev.sensor
            dR = rot_z(ev.angle_rad)  # about the sensor's z axis, the skin normal
            R, p = faults.slip(R, p, t, i, ev.time_s, S[i].T @ ev.displacement_m, dR)
            S[i] = S[i] @ dR
        return R, p

    # -- faults injected at run time ------------------------------------------------------------

    def _update(self, **changes) -> None:
        with self._lock:
            self._faults = replace(self._faults, **changes)

    def inject_slip(
        self,
        sensor: str | int,
        distance_m: float,
        at_time: float | None = None,
        direction=None,
        angle_deg: float = 0.0,
        unstreamed: bool = False,
    ) -> SlipEvent:
        """Make `sensor` slide `distance_m` along the skin at `at_time` (default: just after the last time
        streamed). `direction` is a 3-vector in the body's bone frame (default: a seeded direction in the
        skin's plane); `angle_deg` turns the sensor about the skin normal too. `unstreamed`: refuse an
        `at_time` whose poses were already handed out (a live stream cannot take a slip back). Returns
        the event (`.as_dict(names)`: as `slips` lists it)."""
        i = self.index(sensor)
        if not 0.0 <= float(distance_m) < 0.5:
            raise SimulatorError(f"slip distance {distance_m} m should be between 0 and 0.5 m")
        with self._lock:
            if unstreamed and at_time is not None and float(at_time) <= self._last_time:
                raise SimulatorError(f"the performer's clock is already at {self._last_time:.3f} s; "
                                     f"ask for a slip after that, not at {float(at_time):.3f} s")
            when = self._last_time + 1e-9 if at_time is None else float(at_time)
            S_now = self._sensor_frames(self._faults.slips, when)[0][i]
            if direction is None:
                rng = np.random.default_rng([self.seed, i, len(self._faults.slips), 0x5119])
                a = rng.uniform(0, 2 * np.pi)
                direction = S_now @ np.array([np.cos(a), np.sin(a), 0.0])  # in the skin's plane
            d = np.asarray(direction, dtype=float)
            if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) == 0:
                raise SimulatorError("slip direction must be a non-zero 3-vector in the body's bone frame")
            ev = SlipEvent(when, i, float(distance_m) * d / np.linalg.norm(d), float(np.radians(angle_deg)))
            self._faults = replace(self._faults, slips=self._faults.slips + (ev,))
        return ev

    def set_dropout(self, prob: float, burst_s: float = 0.0) -> None:
        """Lose each sensor-frame with probability `prob` (in bursts of `burst_s` seconds if > 0)."""
        if not 0.0 <= prob <= 1.0 or burst_s < 0:
            raise SimulatorError(f"dropout probability must be in 0..1 and burst ≥ 0 s, not {prob}, {burst_s}")
        self._update(dropout=float(prob), dropout_burst_s=float(burst_s))

    def set_unit_scale(self, scale: float) -> None:
        """Report every position times `scale` (a tracker whose unit calibration is off)."""
        faults.unit_scale(np.zeros(3), scale)  # validates
        self._update(unit_scale=float(scale))

    def set_noise(self, noise: str | None = "tracker", scale: float = 1.0) -> None:
        """Tracker noise on ("tracker", with every std times `scale`) or off (None)."""
        if noise not in NOISE_KINDS or scale < 0:
            raise SimulatorError(f"noise must be 'tracker' or None with scale ≥ 0, not {noise!r}, {scale}")
        self._update(noise=noise, noise_scale=float(scale))

    def set_hemisphere(self, hemisphere: str | None) -> None:
        """Mirror sensors outside this hemisphere, as the Flock does (None: report true positions)."""
        if hemisphere is not None:
            faults.hemisphere_mask(np.zeros((1, 3)), hemisphere)  # validates
        self._update(hemisphere=hemisphere)

    def set_quantise(self, full_scale_in: float | None, orientation: str = "matrix") -> None:
        """Round poses to the Flock's 14-bit words at this full scale (None: full precision)."""
        if full_scale_in is not None:
            faults.quantise(np.eye(3)[None, None], np.zeros((1, 1, 3)), float(full_scale_in), orientation)
        self._update(quantise_in=None if full_scale_in is None else float(full_scale_in), orientation=orientation)

    def set_routine(self, routine: str, period: float | None = None) -> None:
        """Switch to another routine (same body and seed); frames asked for from now on follow it.

        Safe while another thread streams: the new routine replaces the old under the performer's lock."""
        if routine not in ROUTINES:
            raise SimulatorError(f"unknown routine {routine!r}; choose one of {', '.join(ROUTINES)}")
        motion = make_routine(self.model, routine, 60.0 if period is None else period, self.rate_hz, self.seed,
                              period=period)
        with self._lock:
            self.motion = motion

    def clear_faults(self) -> None:
        """Remove slips, dropouts, scale error, mirroring and quantisation (the noise setting stays)."""
        with self._lock:
            self._faults = _Faults(noise=self._faults.noise, noise_scale=self._faults.noise_scale)

    @property
    def slips(self) -> list[dict]:
        with self._lock:
            return [e.as_dict(self.names) for e in sorted(self._faults.slips, key=lambda e: e.time_s)]

    # -- ground truth ---------------------------------------------------------------------------

    def _sensor_frames(self, slips, at_time: float):
        S, s = self.model.sensor_rotation.copy(), self.model.sensor_offset.copy()
        for ev in sorted(slips, key=lambda e: e.time_s):
            if ev.time_s <= at_time:
                s[ev.sensor] = s[ev.sensor] + ev.displacement_m
                S[ev.sensor] = S[ev.sensor] @ rot_z(ev.angle_rad)
        return S, s

    def model_at(self, at_time: float | None = None) -> BodyModel:
        """The body model with the sensor placements in force at `at_time` (default: now, all slips)."""
        with self._lock:
            slips = self._faults.slips
        when = np.inf if at_time is None else float(at_time)
        S, s = self._sensor_frames(slips, when)
        return replace(self.model, sensor_rotation=S, sensor_offset=s)

    def truth(self, at_time: float | None = None) -> dict:
        """Ground truth (design.md §5 fit shape) for the placements in force at `at_time`, plus the
        slips so far, each with the joints it moved."""
        out = self.model_at(at_time).truth()
        events = []
        for ev in self.slips:
            i = self.model.index(ev["sensor"])
            # A joint is named by its child body: the sensor's own inboard joint and its children's.
            own = [i] if self.model.parent[i] >= 0 else []
            ev["joints"] = [self.names[k] for k in own + self.model.children(i)]
            events.append(ev)
        out["slip_events"] = events
        # Joint c, l above are the rest placements; with STA the sensors move about them with the pose.
        out["soft_tissue"] = {"size_mm": 0.0} if self.sta is None else self.sta.describe()
        with self._lock:
            motion = self.motion
        out["routine"] = motion.name
        out["period_s"] = motion.period
        out["seed"] = self.seed
        return out
