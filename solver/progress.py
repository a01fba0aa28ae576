"""The one definition of calibration progress: how far each sensor's joint is from calibrated, the overall
figure, `done`, and what is missing and why. The solver decides it from fits (`standing`: one fit;
`progress_tracker.ProgressTracker`: a session, fit after fit) and returns a typed `Progress`; the service
publishes its `to_dict()` (REST, websocket, SQLite), the kiosk ring, the dashboard and `flockcal report`
only display it.

Every sensor but the root counts. Its joint (the one named by it, design.md §5) counts 1 once it is
*done*: determined (design.md §3a) with the centre pinned to the target along every direction it needs
(all three for a ball, the two pinned ones for a hinge), between two bodies the tree has settled. A sensor
still riding rigidly on its neighbour, or whose joint is not determined, counts 0. Within a session a done
joint stays done (`ProgressTracker`) unless its sensor slips or its fit is really lost (`lost`), so the
standard error wobbling about the target moves nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

from flockcal.names import joint_name, readable_body
from flockcal.solver.calibration import Calibration
from flockcal.solver.progress_words import hint_sentence, why_not_done

# A done joint is undone by a loss of fit, not a wobble: when it is no longer determined and the error
# along a direction it needs exceeds this multiple of the error it was counted at (`lost`), or nothing
# turned along it any more. A joint's error is an upper confidence bound that moves as batch-means blocks
# complete; twice the target is well outside that (a 4x variance), while a sensor moved on the skin is the
# slip monitor's to report.
LOSS_FACTOR = 2.0

# A joint is counted once it has met the target over this much session time, fit after fit. In the first
# second of a take the solver's batch-means errors rest on one or two 64-frame blocks and a joint can read
# determined and lose it again a few fits later (the elbow at 0.4–0.9 s on a simulated kiosk guest). Over 20
# simulated guests the ring went back 19 times with no hold, once with 0.5 s and never with 1 s.
CONFIRM_S = 1.0

# Kiosk: a joint determined to the kiosk's tolerance but not yet steady counts this share of one.
SETTLING_SHARE = 0.8

# Below 1 until done: a ring at "100 %" must mean done, even when every joint has been done once but the
# newest fit still waits on one of them to be pinned again.
NOT_DONE_CAP = 0.99

# The kiosk profile (issue #30): what an avatar needs, judged from what the take shows under soft tissue.
# A joint is determined to 10 mm (design.md §3a, read at its 80 % bound: skin makes that bound shrink as
# 1/√t over minutes while the skeleton stopped changing long before). Where its error is mostly skin (the
# batch-means error twice the white-noise one or more), it counts once the white-noise part is within the
# stage's 3.5 mm and more data has visibly stopped changing it: moved on (its information along the
# least-turned direction it needs grew by a tenth since it was first determined) and its bones and its
# place in the tree held within 3 mm over the last 2 s. On white residuals (rigid sensors) more frames do
# shrink the error, and it waits for the stage's 3.5 mm. Measured on 20 simulated guests (benchmarks/
# bench_calibrate_time.py, docs/service.md "Time to calibrate"), 12 mm soft tissue: done 22.8-33.9 s,
# median 24.2 s, bones at done within 3.1 mm of the same guest's after 120 s; rigid: median 20.0 s. A joint
# counted as soon as its error read 3.5 mm though that error was mostly skin left one guest's bone 5.4 mm
# from where 120 s put it; a 5 mm tolerance, or steadiness over information instead of time, kept guests
# for the routine's second loop (median 37-55 s) for bones that moved no more.
KIOSK_TOLERANCE_M = 0.010
KIOSK_STEADY_S = 2.0
KIOSK_STEADY_M = 0.003
KIOSK_GROWTH = 0.1


class JointState(str, Enum):
    """A sensor's standing, furthest from calibrated first (the order `missing` lists ties in)."""

    RIGID = "rigid"  # no joint yet: it moves rigidly with its neighbour
    NOT_TURNED = "not_turned"  # nothing turned beyond noise about a direction it needs
    UNDETERMINED = "undetermined"
    UNSETTLED = "unsettled"  # pinned, but its child fits another parent as well
    PINNING = "pinning"  # determined to the tolerance, not yet to the target
    SETTLING = "settling"  # kiosk: pinned, more data may still change it
    CONFIRMING = "confirming"  # at the target, counted once it has held for CONFIRM_S
    DONE = "done"


STATES = tuple(s.value for s in JointState)
_STATE_ORDER = {s: k for k, s in enumerate(JointState)}


@dataclass(frozen=True)
class Steadiness:
    """The kiosk's test that more data no longer changes a joint. Where its error is mostly skin
    (`skin_ratio` × the white-noise error or more): the part of its error that more frames shrink (the
    classical, white-noise error) within `noise_m` along every direction it needs, and its bones and its
    parent held within `within_m` over the last `window_s` of session time after it moved on by `growth` of
    its information. Where it is not: pinned to `noise_m` (the stage's target), as on a stage."""

    window_s: float = KIOSK_STEADY_S
    within_m: float = KIOSK_STEADY_M
    growth: float = KIOSK_GROWTH
    noise_m: float = 0.005 / math.sqrt(2.0)
    # The error at least this multiple of the white-noise error: correlated residuals (skin) set it, and more
    # frames of the same motion do not shrink it. Measured at 20 s of the kiosk routine: 2.8-12 for the 15
    # joints of a guest with 12 mm of soft tissue, 1.0-1.8 on rigid sensors.
    skin_ratio: float = 2.0


@dataclass(frozen=True)
class Profile:
    """How a session decides a joint is calibrated. "stage" (an operator's capture stage, the default):
    determined to the tolerance and pinned to `target_m`. "kiosk" (a guest's avatar): determined to the
    kiosk's tolerance and steady (`Steadiness`)."""

    name: str
    tolerance_m: float
    target_m: float
    steady: Steadiness | None = None

    @property
    def rule(self) -> str:
        """The rule in plain words (the kiosk page's help, the progress document)."""
        if self.steady is None:
            return (f"A joint counts once its centre is pinned to {1000 * self.target_m:.1f} mm along every "
                    "direction it needs, and held so for a second; done when every joint counts.")
        return (f"A joint counts once the data pin its centre to {1000 * self.tolerance_m:.0f} mm in every "
                f"direction it needs and more data no longer changes it: after it has moved on a little, its "
                f"bones held within {1000 * self.steady.within_m:.0f} mm over {self.steady.window_s:g} s. "
                "You are done when every joint counts.")


PROFILES = ("stage", "kiosk")


def profile(name: str, tolerance_m: float, target_m: float | None = None) -> Profile:
    """The named profile; "stage" takes the service's --tolerance-mm and --target-mm."""
    if name == "kiosk":
        return Profile("kiosk", KIOSK_TOLERANCE_M, KIOSK_TOLERANCE_M, Steadiness())
    if name == "stage":
        return Profile("stage", float(tolerance_m), default_target(tolerance_m) if target_m is None else float(target_m))
    raise ValueError(f"unknown profile {name!r}; choose one of {', '.join(PROFILES)}")


def default_target(tolerance_m: float) -> float:
    """The joint-centre error counted as calibrated unless one is given: the tolerance / √2. A bone spans two
    joint centres, each pinned to the target along every direction; errors of its two ends add in quadrature,
    so the bone is then held to the tolerance (5 mm by default: bones within 5 mm at done, the kiosk's aim).
    On 20 simulated kiosk guests the full 5 mm left one hinge-ended bone 5.8 mm off at done, 3.5 mm none
    over 4.3 mm, for 0.3 s more (benchmarks/bench_calibrate_time.py)."""
    return float(tolerance_m) / math.sqrt(2.0)


# --- what progress reads of a fit --------------------------------------------------------------------
@dataclass(frozen=True)
class JointFit:
    """What progress reads of one tree joint of a fit (metres; inf where nothing turned)."""

    child: str
    parent: str
    hinge: bool
    determined: bool
    error: tuple  # the centre's error along its three least-turned directions, ascending
    noise: tuple  # the white-noise part of it (kiosk)
    coverage: tuple  # (3,), 0 where unknown

    def needed(self, hinge: bool | None = None, noise: bool = False) -> tuple:
        """The error (or its white-noise part) along the directions the joint needs: all three for a ball
        joint, the two pinned ones for a hinge (`hinge` overrides the joint's own flag)."""
        err = self.noise if noise else self.error
        return err[1:] if (self.hinge if hinge is None else hinge) else err


@dataclass(frozen=True)
class FitFacts:
    """The fields of one fit progress reads, by name, off a `Calibration` (the live service, the report, a
    re-solve; a §5 dict, a fit written out by hand, is decoded into one first)."""

    sensors: tuple
    root: str | None
    parent: Mapping  # {child: parent}
    joints: Mapping  # {child: JointFit}, the tree's joints
    groups: Mapping  # {sensor: its rigid group's members}
    ambiguous: Mapping  # {child: [parents it fits equally well]}
    frames: int
    bones: Mapping  # {(body, from_joint, to_joint): length (m)}, drawn bones only
    joint_names: Mapping = field(default_factory=dict)  # {child: the joint's name, "left knee"} (§5 joints[].name)

    @classmethod
    def of(cls, fit) -> "FitFacts":
        """`fit` (a Calibration, FitFacts, or a §5 dict: decoded first by `calibration_from_json`, the one
        parser) as FitFacts."""
        if isinstance(fit, FitFacts):
            return fit
        if not isinstance(fit, Calibration):
            from flockcal.solver.calibration_json import calibration_from_json

            fit = calibration_from_json(fit)
        return cls.of_calibration(fit)

    @classmethod
    def of_calibration(cls, cal: Calibration) -> "FitFacts":
        nm = cal.names
        j = cal.joints
        determined, err = j.determined.tolist(), _finite(j.direction_error, math.inf)
        noise = _finite(j.noise_error, math.inf)
        optical = cal.optical is not None
        if optical:
            # An optical fit's joints are judged from the bodies' poses (solver/optical/exercised.py), not by
            # the pair fit's statistics; a joint it could not judge counts as not determined, and no
            # white-noise share is known.
            determined, err = _judged(cal.optical.joint_decisions, len(j))
            noise = [[math.inf] * 3 for _ in range(len(j))]
        cov = _finite(j.coverage, 0.0)
        joints = {}
        for k, ((child, par), hinge, det) in enumerate(zip(j.pairs.tolist(), j.hinge.tolist(), determined)):
            joints[nm[child]] = JointFit(nm[child], nm[par], bool(hinge), bool(det), tuple(err[k]), tuple(noise[k]),
                                         tuple(cov[k]))
        b = cal.bones
        bones = {(nm[body], nm[frm] if frm >= 0 else None, nm[to]): length
                 for body, frm, to, length in zip(b.body.tolist(), b.from_joint.tolist(), b.to_joint.tolist(),
                                                  b.length.tolist()) if math.isfinite(length)}
        free = not (cal.known_skeleton or optical)  # a saved skeleton's or optical fit: no rigid groups, no ambiguity
        groups = {nm[i]: tuple(nm[x] for x in g) for g in (cal.rigid_groups if free else ()) for i in g}
        ambiguous = {nm[c]: [nm[p] for p in ps] for c, ps, _ in (cal.ambiguous if free else ())}
        named = dict(zip((nm[c] for c in j.pairs[:, 0].tolist()), cal.joint_names()))
        return cls(tuple(nm), nm[cal.root], cal.parent_map(), joints, groups, ambiguous, int(cal.frames), bones, named)


def _judged(decisions, n: int) -> tuple[list, list]:
    """(determined, direction error as (J, 3) floats with inf for unknown) of an optical fit's joint decisions
    (`OpticalExtras.joint_decisions`; none: nothing judged)."""
    decisions = decisions or ({},) * n
    determined = [bool(x.get("determined")) for x in decisions]
    err = [[math.inf if v is None else float(v) for v in (x.get("direction_error_m") or (None,) * 3)] for x in decisions]
    return determined, [[v if math.isfinite(v) else math.inf for v in row] for row in err]


def _finite(a, fill: float) -> list:
    """An (n, 3) array as lists of floats, `fill` where not finite (as its §5 JSON's null reads)."""
    return [[x if math.isfinite(x) else fill for x in row] for row in a.tolist()]


def lost(joint: JointFit | None, hinge: bool, counted_at_m: float) -> bool:
    """The loss rule, for a joint counted (done, or a pinning share) at `counted_at_m` as a hinge or not:
    no longer determined, and off by more than LOSS_FACTOR times that along a direction it needed (or
    nothing turned along it any more). A done joint was counted at the target, a pinning share at the
    tolerance it was determined to."""
    return (joint is not None and not joint.determined
            and max(joint.needed(hinge=hinge)) > LOSS_FACTOR * counted_at_m)


# --- the typed result ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Undone:
    """Why a joint calibrated once is not any more: "slip" (of `sensor`, at `time_s`), "loss" (`lost`),
    or "tree" (the tree now joins it to `parent`; it was calibrated against `was`)."""

    reason: str
    time_s: float
    sensor: str
    parent: str | None = None
    was: str | None = None

    def to_dict(self) -> dict:
        d = {"reason": self.reason, "time_s": self.time_s, "sensor": self.sensor}
        if self.reason == "tree":
            d.update(parent=self.parent, was=self.was)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "Undone":
        return cls(d["reason"], d["time_s"], d["sensor"], d.get("parent"), d.get("was"))


@dataclass(frozen=True)
class JointProgress:
    """One sensor's joint in a progress document. `progress` is its share (1 when done) at full precision;
    `why` (not done: in plain words) and `hint` (not done: the operator's sentence)."""

    joint: str  # the joint, named by its child (= the sensor)
    parent: str | None
    label: str  # as people name it ("left elbow")
    state: JointState
    progress: float
    done: bool
    error_m: float | None  # the centre's error along the worst direction it needs
    why: str | None = None
    undone: Undone | None = None
    hint: str | None = None

    def entry(self) -> dict:
        """Its `missing` entry (docs/service.md)."""
        return {"joint": self.joint, "parent": self.parent, "label": self.label, "state": self.state.value,
                "why": self.why, "undone": None if self.undone is None else self.undone.to_dict()}


@dataclass(frozen=True)
class Progress:
    """A session's (or one fit's) progress: the published figure, done, and each sensor's joint in the
    tree's order (`joints`), `missing` naming those not done, furthest from calibrated first.
    `to_dict()` is the document the service publishes (docs/service.md), `from_dict` reads it back."""

    state: str  # "no_fit", "calibrating" or "done"
    progress: float  # 0..1 as published (4 decimals): 1 only when done
    percent: int  # whole percent, rounded down: what the ring shows
    done: bool
    done_at_s: float | None
    target_m: float
    joints_needed: int
    joints: tuple = ()  # (JointProgress, …)
    missing: tuple = ()  # the joints (names) not done, furthest from calibrated first
    tracked: bool = False  # a session's (ProgressTracker): `stalled_s` and `prompt` are published
    stalled_s: float | None = None
    prompt: str | None = None
    profile: str | None = None  # the profile a session follows, and its `rule` in words
    rule: str | None = None
    note: str | None = None  # before the first fit: why there is none
    _by_joint: dict = field(default=None, init=False, repr=False, compare=False)

    @property
    def joints_done(self) -> int:
        return sum(1 for j in self.joints if j.done)

    def joint(self, name: str) -> JointProgress:
        if self._by_joint is None:
            object.__setattr__(self, "_by_joint", {j.joint: j for j in self.joints})
        return self._by_joint[name]

    def missing_joints(self) -> list[JointProgress]:
        return [self.joint(x) for x in self.missing]

    def to_dict(self) -> dict:
        todo = self.missing_joints()
        out = {
            "state": self.state, "progress": self.progress, "percent": self.percent, "done": self.done,
            "done_at_s": self.done_at_s, "target_m": self.target_m, "joints_done": self.joints_done,
            "joints_needed": self.joints_needed,
            "missing": [j.entry() for j in todo],
            "joint_progress": [{**j.entry(), "progress": 1.0 if j.done else round(j.progress, 4), "done": j.done,
                                "error_m": j.error_m} for j in self.joints],
            "hints": [{"joint": j.joint, "label": j.label, "progress": round(j.progress, 3), "hint": j.hint}
                      for j in todo],
        }
        if self.tracked:
            out.update(stalled_s=self.stalled_s, prompt=self.prompt)
        if self.profile is not None:
            out.update(profile=self.profile, rule=self.rule)
        if self.note is not None:
            out["note"] = self.note
        return out

    @classmethod
    def from_dict(cls, d: Mapping) -> "Progress":
        """The document `to_dict` made, read back: `Progress.from_dict(d).to_dict() == d`."""
        why = {m["joint"]: m for m in d["missing"]}
        hints = {h["joint"]: h for h in d["hints"]}
        joints = []
        for e in d["joint_progress"]:
            h = hints.get(e["joint"])
            joints.append(JointProgress(
                e["joint"], e["parent"], e["label"], JointState(e["state"]),
                _share(e["progress"], h["progress"] if h else None), bool(e["done"]), e["error_m"],
                e["why"], None if e["undone"] is None else Undone.from_dict(e["undone"]), h["hint"] if h else None))
        return cls(d["state"], d["progress"], d["percent"], d["done"], d["done_at_s"], d["target_m"],
                   d["joints_needed"], tuple(joints), tuple(why), "stalled_s" in d, d.get("stalled_s"),
                   d.get("prompt"), d.get("profile"), d.get("rule"), d.get("note"))


def _share(published: float, hinted: float | None) -> float:
    """A joint's share from its two published roundings (4 decimals, and 3 in its hint): where rounding the
    first to 3 decimals misses the second (a 4-decimal figure on a half), the share just beside it that
    gives both."""
    if hinted is None or round(published, 3) == hinted:
        return published
    return published + math.copysign(1e-9, hinted - published)


# --- one fit -------------------------------------------------------------------------------------------
@dataclass
class Standing:
    """A sensor's joint as one fit has it, while progress is worked out (`standing`, ProgressTracker)."""

    joint: str
    parent: str | None
    label: str
    state: JointState
    progress: float
    bodies: tuple  # (frozenset, frozenset): the bodies each end belongs to (rigid groups)
    error_m: float | None = None
    pinned: int = 0  # directions pinned to the tolerance
    hinge: bool = False
    unsettled: str | None = None  # which parents it fits equally well
    settling: str | None = None  # kiosk: the steadiness test it waits for
    done: bool = False
    undone: Undone | None = None
    meets_now: bool = True  # meets the target in this fit
    why: str | None = None


def standing(fit, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False) -> list[Standing]:
    """One entry per sensor but the root, in the fit's tree order, as this fit alone has it (no history).

    state: DONE (determined, pinned to `target_m`, its place in the tree settled); UNSETTLED (pinned,
    but its child fits another parent as well, so which two bodies it joins may change: 0); PINNING
    (determined to the solver's tolerance, not yet to the target: progress (target/error)², the share of the
    frames it needs at this rate, the error falling as 1/√frames); UNDETERMINED (0); NOT_TURNED (nothing
    turned beyond noise about a direction it needs: 0); RIGID (no joint yet, it moves rigidly with its
    neighbour: 0). `tree_fixed`: the tree was given (a hierarchy or a saved skeleton), so it cannot be
    unsettled.
    """
    f = FitFacts.of(fit)
    tol = target_m if tolerance_m is None else tolerance_m
    out = []
    for sensor in (s for s in f.sensors if s != f.root):
        par = f.parent.get(sensor)
        j = f.joints.get(sensor)
        # The bodies each end belongs to: a joint done against one member of a rigid group is the same joint
        # when the group comes apart and the tree re-links it to another member (ProgressTracker).
        bodies = (frozenset(f.groups.get(sensor, (sensor,))), frozenset(f.groups.get(par, (par,))))
        # Named as the fit names it (the humanoid's "left knee"), else from the sensors' names.
        label = f.joint_names.get(sensor) or joint_name(sensor, par)
        if j is None or (par is not None and par in f.groups.get(sensor, ())):
            out.append(Standing(sensor, par, label, JointState.RIGID, 0.0,
                                (frozenset((sensor,)), frozenset((par,)))))
            continue
        worst = max(j.needed())
        it = Standing(sensor, par, label, JointState.DONE, 1.0, bodies,
                      error_m=worst if math.isfinite(worst) else None,
                      pinned=sum(e <= tol for e in j.needed(hinge=False)), hinge=j.hinge)
        if not j.determined:
            it.state = JointState.NOT_TURNED if not math.isfinite(worst) else JointState.UNDETERMINED
            it.progress = 0.0
        elif worst > target_m:
            it.state, it.progress = JointState.PINNING, min(1.0, (target_m / worst) ** 2)
        elif not tree_fixed and len(f.ambiguous.get(sensor, ())) > 1:
            names = " and the ".join(readable_body(x) for x in f.ambiguous[sensor])
            it.state, it.progress = JointState.UNSETTLED, 0.0
            it.unsettled = f"it fits the {names} equally well"
        out.append(it)
    return out


def summarise(items: list[Standing], target_m: float, done: bool, done_at_s: float | None = None) -> Progress:
    """The published document from per-sensor items (each with state, progress, done and undone)."""
    n = len(items)
    mean = sum(1.0 if it.done else it.progress for it in items) / n if n else 0.0
    value = round(1.0 if done else min(mean, NOT_DONE_CAP), 4)
    todo = sorted((it for it in items if not it.done), key=lambda it: (it.progress, _STATE_ORDER[it.state]))
    for it in items:
        it.why = None if it.done else why_not_done(it, target_m)
    if not done and items and not todo:
        # Every joint has been calibrated, but done waits for one fit that pins them all at once: the
        # joints this fit leaves short are what is missing, and they are shown as not done (a chip ticked
        # and a count of 15 / 15 below 100 % told the guest nothing was left).
        todo = [it for it in items if not it.meets_now]
        for it in todo:
            it.done, it.state, it.progress = False, JointState.CONFIRMING, NOT_DONE_CAP
            it.why = "calibrated; waiting for a fit that pins it again together with the others"
    joints = tuple(JointProgress(it.joint, it.parent, it.label, it.state, 1.0 if it.done else it.progress, it.done,
                                 it.error_m, it.why, it.undone, None if it.done else hint_sentence(it))
                   for it in items)
    return Progress("done" if done else "calibrating", value, percent(value), bool(done), done_at_s, target_m, n,
                    joints, tuple(it.joint for it in todo))


def percent(value: float) -> int:
    """The ring's figure: whole percent, rounded down (so "100 %" is done and nothing else)."""
    return int(math.floor(value * 100 + 1e-9))


def progress_of(fit, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False) -> Progress:
    """Progress of one fit on its own (no session history, nothing to confirm over time): what `flockcal
    report` and a re-solved session show. The same document as the live service publishes."""
    items = standing(fit, target_m, tolerance_m, tree_fixed)
    for it in items:
        it.done = it.state is JointState.DONE
    return summarise(items, target_m, bool(items) and all(it.done for it in items))


def waiting(names, target_m: float, note: str) -> Progress:
    """The document before a session has its first fit: nothing is known yet, nothing is done."""
    return Progress("no_fit", 0.0, 0, False, None, target_m, max(len(names) - 1, 0), note=note)
