"""The one definition of calibration progress: how far each sensor's joint is from calibrated, the overall
figure, `done`, and what is missing and why. The service computes it once per fit and publishes it (REST,
websocket); the kiosk ring, the dashboard and `flockcal report` only display it.

Every sensor but the root counts. Its joint (the one named by it, design.md §5) counts 1 once it is
*done*: determined (design.md §3a) with the centre pinned to the target along every direction it needs
(all three for a ball, the two pinned ones for a hinge), between two bodies the tree has settled. A sensor
still riding rigidly on its neighbour, or whose joint is not determined, counts 0. Within a session a done
joint stays done (`ProgressTracker`) unless its sensor slips or its fit is really lost, so the standard
error wobbling about the target moves nothing.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from flockcal.server.coaching import hint_sentence, joint_name, readable_body

# A done joint is undone by a loss of fit, not a wobble: when it is no longer determined and the error
# along a direction it needs exceeds this multiple of the target, or nothing turned along it any more. A
# joint's error is an upper confidence bound that moves as batch-means blocks complete; twice the target is
# well outside that (a 4x variance), while a sensor moved on the skin is the slip monitor's to report.
LOSS_FACTOR = 2.0

# A joint is counted once it has met the target over this much session time, fit after fit. In the first
# second of a take the solver's batch-means errors rest on one or two 64-frame blocks and a joint can read
# determined and lose it again a few fits later (the elbow at 0.4–0.9 s on a simulated kiosk guest). Over 20
# simulated guests the ring went back 19 times with no hold, once with 0.5 s and never with 1 s.
CONFIRM_S = 1.0

# Kiosk: a joint determined to the kiosk's tolerance but not yet steady counts this share of one.
SETTLING_SHARE = 0.8

# A patient prompt once the ring has gained less than STALL_GAIN over STALL_S of session time: a guest who
# stopped moving (standing still with skin-mounted sensors, the ring still creeps up by 0.5 % a second as
# sway pins a joint or two) or one joint that will not come; a moving guest gains a joint (6.7 %) in 2-3 s.
STALL_S = 8.0
STALL_GAIN = 0.1

# Below 1 until done: a ring at "100 %" must mean done, even when every joint has been done once but the
# newest fit still waits on one of them to be pinned again.
NOT_DONE_CAP = 0.99

# A sensor's standing, furthest from calibrated first (the order `missing` lists ties in).
STATES = ("rigid", "not_turned", "undetermined", "unsettled", "pinning", "settling", "confirming", "done")

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
_STATE_ORDER = {s: k for k, s in enumerate(STATES)}


def default_target(tolerance_m: float) -> float:
    """The joint-centre error counted as calibrated unless one is given: the tolerance / √2. A bone spans two
    joint centres, each pinned to the target along every direction; errors of its two ends add in quadrature,
    so the bone is then held to the tolerance (5 mm by default: bones within 5 mm at done, the kiosk's aim).
    On 20 simulated kiosk guests the full 5 mm left one hinge-ended bone 5.8 mm off at done, 3.5 mm none
    over 4.3 mm, for 0.3 s more (benchmarks/bench_calibrate_time.py)."""
    return float(tolerance_m) / math.sqrt(2.0)


def needed_errors(joint: dict, hinge: bool | None = None) -> list[float]:
    """The centre's error (m) along the directions the joint needs, inf where nothing turned: all three for
    a ball joint, the two pinned ones for a hinge (`hinge` overrides the joint's own flag)."""
    err = [math.inf if x is None else float(x) for x in (joint.get("direction_error_m") or (None,) * 3)]
    is_hinge = joint.get("hinge") if hinge is None else hinge
    return err[1:] if is_hinge else err


def standing(fit: dict, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False) -> list[dict]:
    """One entry per sensor but the root, in the fit's tree order, as this fit alone has it (no history):
    {joint (= the sensor: a joint is named by its child), parent, label, state, progress, error_m, pinned,
    unsettled}.

    state: "done" (determined, pinned to `target_m`, its place in the tree settled); "unsettled" (pinned,
    but its child fits another parent as well, so which two bodies it joins may change: 0); "pinning"
    (determined to the solver's tolerance, not yet to the target: progress (target/error)², the share of the
    frames it needs at this rate, the error falling as 1/√frames); "undetermined" (0); "not_turned" (nothing
    turned beyond noise about a direction it needs: 0); "rigid" (no joint yet, it moves rigidly with its
    neighbour: 0). `tree_fixed`: the tree was given (a hierarchy or a saved skeleton), so it cannot be
    unsettled.
    """
    tol = target_m if tolerance_m is None else tolerance_m
    parent = fit.get("parent") or {}
    root = fit.get("root")
    by_child = {j["child"]: j for j in fit.get("joints") or []}
    group_of: dict[str, list] = {}
    for group in fit.get("rigid_groups") or []:
        for name in group:
            group_of[name] = list(group)
    ambiguous = {a["child"]: a.get("parents") or [] for a in fit.get("ambiguous") or []}
    out = []
    for sensor in (s for s in fit.get("sensors") or [] if s != root):
        par = parent.get(sensor)
        j = by_child.get(sensor)
        item = {"joint": sensor, "parent": par, "label": joint_name(sensor, par), "error_m": None,
                "pinned": 0, "hinge": False, "unsettled": None}
        if j is None or (par is not None and par in group_of.get(sensor, ())):
            item.update(state="rigid", progress=0.0, bodies=(frozenset((sensor,)), frozenset((par,))))
            out.append(item)
            continue
        worst = max(needed_errors(j))
        item["error_m"] = worst if math.isfinite(worst) else None
        item["pinned"] = sum(e <= tol for e in needed_errors(j, hinge=False))
        item["hinge"] = bool(j.get("hinge"))
        if not j.get("determined"):
            item.update(state="not_turned" if not math.isfinite(worst) else "undetermined", progress=0.0)
        elif worst > target_m:
            item.update(state="pinning", progress=min(1.0, (target_m / worst) ** 2))
        else:
            item.update(state="done", progress=1.0)
            if not tree_fixed and len(ambiguous.get(sensor, ())) > 1:
                names = " and the ".join(readable_body(x) for x in ambiguous[sensor])
                item.update(state="unsettled", progress=0.0, unsettled=f"it fits the {names} equally well")
        # The bodies each end belongs to: a joint done against one member of a rigid group is the same joint
        # when the group comes apart and the tree re-links it to another member (ProgressTracker).
        item["bodies"] = (frozenset(group_of.get(sensor, (sensor,))), frozenset(group_of.get(par, (par,))))
        out.append(item)
    return out


def _why(item: dict, target_m: float) -> str:
    undone = item.get("undone")
    if undone and undone["reason"] == "slip":
        return f"the {readable_body(undone['sensor'])} sensor slipped at {undone['time_s']:.1f} s: measured afresh since"
    if undone and undone["reason"] == "loss":
        return "no longer fits as it did when calibrated"
    if undone and undone["reason"] == "tree":
        return (f"the tree now joins it to the {readable_body(undone['parent'])} "
                f"(it was calibrated against the {readable_body(undone['was'])})")
    state = item["state"]
    if state == "rigid":
        return f"has not moved relative to the {readable_body(item['parent'] or '')} yet"
    if state == "not_turned":
        return "not determined: it has hardly turned yet"
    if state == "undetermined":
        return f"not determined: its centre is pinned along {item['pinned']} of 3 directions"
    if state == "unsettled":
        return f"pinned, but its place in the tree is not settled: {item['unsettled']}"
    if state == "confirming":
        return "pinned; counted once it holds for a moment"
    if state == "settling":
        return item.get("settling") or "pinned; counted once more movement no longer changes it"
    return f"pinned to {1000 * item['error_m']:.1f} mm, target {1000 * target_m:.1f} mm"


def summarise(items: list[dict], target_m: float, done: bool, done_at_s: float | None = None) -> dict:
    """The published document from per-sensor items (each with state, progress, done and undone)."""
    n = len(items)
    mean = sum(1.0 if it["done"] else it["progress"] for it in items) / n if n else 0.0
    value = round(1.0 if done else min(mean, NOT_DONE_CAP), 4)
    todo = sorted((it for it in items if not it["done"]), key=lambda it: (it["progress"], _STATE_ORDER[it["state"]]))
    for it in items:
        it["why"] = None if it["done"] else _why(it, target_m)
    if not done and items and not todo:
        # Every joint has been calibrated, but done waits for one fit that pins them all at once: the
        # joints this fit leaves short are what is missing, and they are shown as not done (a chip ticked
        # and a count of 15 / 15 below 100 % told the guest nothing was left).
        todo = [it for it in items if not it.get("meets_now", True)]
        for it in todo:
            it.update(done=False, state="confirming", progress=NOT_DONE_CAP,
                      why="calibrated; waiting for a fit that pins it again together with the others")
    keys = ("joint", "parent", "label", "state", "why", "undone")
    return {
        "state": "done" if done else "calibrating",
        "progress": value,
        # The ring's figure: whole percent, rounded down (so "100 %" is done and nothing else).
        "percent": int(math.floor(value * 100 + 1e-9)),
        "done": bool(done),
        "done_at_s": done_at_s,
        "target_m": target_m,
        "joints_done": sum(1 for it in items if it["done"]),
        "joints_needed": n,
        "missing": [{k: it[k] for k in keys} for it in todo],
        "joint_progress": [{**{k: it[k] for k in keys}, "progress": 1.0 if it["done"] else round(it["progress"], 4),
                            "done": it["done"], "error_m": it["error_m"]} for it in items],
        "hints": [{"joint": it["joint"], "label": it["label"], "progress": round(it["progress"], 3),
                   "hint": hint_sentence(it)} for it in todo],
    }


def progress_of(fit: dict, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False) -> dict:
    """Progress of one fit on its own (no session history, nothing to confirm over time): what `flockcal
    report` and a re-solved session show. The same document as the live service publishes."""
    items = standing(fit, target_m, tolerance_m, tree_fixed)
    for it in items:
        it["done"] = it["state"] == "done"
        it["undone"] = None
    return summarise(items, target_m, bool(items) and all(it["done"] for it in items))


def waiting(names, target_m: float, note: str) -> dict:
    """The document before a session has its first fit: nothing is known yet, nothing is done."""
    return {"state": "no_fit", "progress": 0.0, "percent": 0, "done": False, "done_at_s": None,
            "target_m": target_m, "joints_done": 0, "joints_needed": max(len(names) - 1, 0), "missing": [],
            "joint_progress": [], "hints": [], "note": note}


class ProgressTracker:
    """Progress of one session, fit after fit. A joint is done once it has been "done" in the sense of
    `standing` for CONFIRM_S; it then stays done until a slip of one of its sensors or a real loss of fit
    (LOSS_FACTOR) undoes it, and its entry says why until it is done again. `done` (the whole session)
    needs every joint done and one fit in which every joint meets the target at once.

    Joints are keyed by their two bodies, so re-rooting the tree keeps them. `slip()` takes the service's
    slip events; fits are stamped with the slip `epoch` their accumulator copy had, so a fit begun before
    a slip was applied cannot mark that sensor's joints done again.
    """

    def __init__(self, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False,
                 confirm_s: float = CONFIRM_S, steady: Steadiness | None = None):
        self.target_m = float(target_m)
        self.tolerance_m = self.target_m if tolerance_m is None else float(tolerance_m)
        self.tree_fixed = bool(tree_fixed)
        self.confirm_s = float(confirm_s)
        self.steady = steady
        self.profile: Profile | None = None
        self._ring = 0.0  # the figure last published (`_hold_ring`)
        self._history: deque = deque()  # (time_s, published figure), for `_stall`
        # The entries of `_history` newer than every later lower-or-equal figure ((index, time_s, figure),
        # figures rising towards the newest): where `_stall`'s backward search can end. `_hist_gone`: entries
        # trimmed off `_history` so far, `_hist_n`: ever appended (indices).
        self._lows: deque = deque()
        self._hist_n = self._hist_gone = 0
        self._recent: deque = deque()  # (time_s, {child: parent}, {bone key: length}) over the steadiness window
        self._first_info: dict[frozenset, float] = {}  # pair → its information when it was first determined
        self.latched: dict[frozenset, dict] = {}  # pair → {hinge, time_s}: done
        self.meeting: dict[frozenset, float] = {}  # pair → session time since which it has met the target
        self.undone: dict[frozenset, dict] = {}  # pair → {reason, time_s, sensor}: done once, undone since
        self.slipped: dict[str, int] = {}  # sensor → epoch of its latest slip
        self.best: dict[frozenset, dict] = {}  # pair → {value, hinge}: the best share a pinning joint reached
        self.pinning: dict[frozenset, float] = {}  # pair → session time since which it has been determined
        self.done_parent: dict[str, str] = {}  # sensor → the parent it was last done against
        # sensor → the share its joint last showed: the ring holds it through tree re-links (#19)
        self.floor: dict[str, float] = {}
        self._credited: dict[str, frozenset] = {}  # sensor → the pair its floor was reached with
        self.done = False
        self.done_at_s: float | None = None
        self.latest: dict | None = None

    @classmethod
    def for_profile(cls, prof: Profile, tree_fixed: bool = False) -> "ProgressTracker":
        """A session's tracker under `prof` ("stage" or "kiosk"); its documents name the profile and its rule."""
        tracker = cls(prof.target_m, prof.tolerance_m, tree_fixed, steady=prof.steady)
        tracker.profile = prof
        return tracker

    def slip(self, event: dict, epoch: int) -> list[str]:
        """Undo every done joint of the slipped sensor(s) (a swap: both); returns the joints undone."""
        sensors = {s for s in (event.get("sensors") or [event.get("sensor")]) if s}
        when = float(event.get("time_s") or 0.0)
        for s in sensors:
            self.slipped[s] = int(epoch)
        for pair in [p for p in self.meeting if p & sensors]:
            del self.meeting[pair]
        for pair in [p for p in self.best if p & sensors]:
            del self.best[pair]
        for pair in [p for p in self.pinning if p & sensors]:
            del self.pinning[pair]
        for pair in [p for p in self._first_info if p & sensors]:
            del self._first_info[pair]
        for child in [c for c in self.floor if c in sensors or self.done_parent.get(c) in sensors
                      or self._credited.get(c, frozenset()) & sensors]:
            del self.floor[child]
        # The monitor confirms a slip some 0.2-1 s after its onset; a joint of that sensor whose fit was
        # lost in between lost it to the slip, and its entry should say so rather than "loss".
        lost = [p for p, u in self.undone.items() if p & sensors and u["reason"] == "loss" and u["time_s"] >= when]
        hit = []
        for pair in [p for p in self.latched if p & sensors]:
            hit.append(self.latched.pop(pair)["joint"])
            lost.append(pair)
        for pair in lost:
            self.undone[pair] = {"reason": "slip", "time_s": when, "sensor": sorted(pair & sensors)[0]}
        return sorted(hit)

    def update(self, fit: dict, time_s: float, epoch: int = 0) -> dict:
        """The session's progress after a new fit (its data up to `time_s`, session clock)."""
        items = standing(fit, self.target_m, self.tolerance_m, self.tree_fixed)
        by_child = {j["child"]: j for j in fit.get("joints") or []}
        if self.steady is not None:
            self._steadiness(items, fit, by_child, float(time_s))
        self._carry_over(items)
        all_clear = bool(items)
        for it in items:
            pair = frozenset((it["joint"], it["parent"]))
            j = by_child.get(it["joint"])
            meets = it["state"] == "done"
            it["meets_now"] = meets
            all_clear &= meets
            stale = max(self.slipped.get(s, -1) for s in pair) > epoch  # a fit begun before that slip
            latch = self.latched.get(pair)
            if latch is not None and j is not None and not meets and not j.get("determined"):
                if max(needed_errors(j, hinge=latch["hinge"])) > LOSS_FACTOR * self.target_m:
                    del self.latched[pair]
                    self.undone[pair] = {"reason": "loss", "time_s": float(time_s), "sensor": it["joint"]}
                    self.floor.pop(it["joint"], None)
                    latch = None
            if latch is None:
                if meets and not stale:
                    since = self.meeting.setdefault(pair, float(time_s))
                    if time_s - since >= self.confirm_s - 1e-9:
                        latch = self.latched[pair] = {"joint": it["joint"], "hinge": bool(j.get("hinge")),
                                                      "time_s": float(time_s), "bodies": it["bodies"]}
                        self.undone.pop(pair, None)
                    else:
                        it.update(state="confirming", progress=0.0)
                else:
                    self.meeting.pop(pair, None)
            it["done"] = latch is not None
            it["undone"] = None
            if not it["done"]:
                self._hold(it, pair, j, time_s, stale)
            if it["done"]:
                it["state"] = "done"  # done stays done through a wobble of the newest fit
                self.done_parent[it["joint"]] = it["parent"]
            elif pair in self.undone:
                u = self.undone[pair]
                it["undone"] = {"reason": u["reason"], "time_s": round(u["time_s"], 3), "sensor": u["sensor"]}
            elif self.done_parent.get(it["joint"], it["parent"]) != it["parent"]:
                it["undone"] = {"reason": "tree", "time_s": round(float(time_s), 3), "sensor": it["joint"],
                                "parent": it["parent"], "was": self.done_parent[it["joint"]]}
        self._hold_floor(items)
        every = bool(items) and all(it["done"] for it in items)
        # Stage: one fit must also pin every joint at once. Kiosk: each joint counted only once it held still,
        # so every joint counted is done (and the ring never shows every joint ticked below 100 %).
        if not self.done and every and (all_clear or self.steady is not None):
            self.done, self.done_at_s = True, round(float(time_s), 3)
        elif self.done and not every:
            self.done, self.done_at_s = False, None
        self.latest = summarise(items, self.target_m, self.done, self.done_at_s)
        self._hold_ring(self.latest, items)
        self._stall(self.latest, float(time_s))
        if self.profile is not None:
            self.latest.update(profile=self.profile.name, rule=self.profile.rule)
        return self.latest

    def _steadiness(self, items: list[dict], fit: dict, by_child: dict, time_s: float) -> None:
        """Kiosk: a pinned joint ("done" in `standing`) counts only once more data no longer changes it;
        until then it is "settling", and its entry says which test it waits for."""
        st = self.steady
        bones = {(b["body"], b["from_joint"], b["to_joint"]): b["length_m"] for b in fit.get("bones") or []
                 if b.get("length_m") is not None}
        parent = dict(fit.get("parent") or {})
        self._recent.append((time_s, parent, bones))
        while len(self._recent) > 1 and self._recent[1][0] <= time_s - st.window_s:
            self._recent.popleft()
        covered = self._recent[0][0] <= time_s - st.window_s + 1e-9
        frames = float(fit.get("frames") or 0)
        for it in items:
            pair = frozenset((it["joint"], it["parent"]))
            j = by_child.get(it["joint"])
            if j is None or not j.get("determined"):
                self._first_info.pop(pair, None)
                continue
            cov = j.get("coverage") or [0.0, 0.0, 0.0]
            info = frames * max(float(cov[1 if j.get("hinge") else 0] or 0.0), 0.0)
            # Since it was first determined (a place in the tree still unsettled does not restart it).
            first = self._first_info.setdefault(pair, info)
            if it["state"] != "done":
                continue
            child = it["joint"]
            mine = [k for k in bones if child in (k[1], k[2])]
            moved = 0.0
            for _, par, past in self._recent:
                if par.get(child) != it["parent"] or any(k not in past for k in mine):
                    moved = math.inf
                    break
                moved = max([moved, *(abs(past[k] - bones[k]) for k in mine)])
            err = max(needed_errors(j))
            noise = max(needed_errors({"direction_error_m": j.get("noise_error_m"), "hinge": j.get("hinge")}))
            skin = err >= st.skin_ratio * noise
            if err <= st.noise_m and not skin:
                continue  # pinned as firmly as the stage asks on white residuals: more frames would only confirm it
            if not skin:
                # White residuals (no skin to speak of): more frames do shrink the error, so wait for them.
                it.update(state="pinning", progress=min(1.0, (st.noise_m / err) ** 2))
                continue
            if noise > st.noise_m:
                why = (f"pinned to {1000 * self.tolerance_m:.0f} mm; counted once the frames pin it to "
                       f"{1000 * st.noise_m:.1f} mm" + (f" (now {1000 * noise:.1f} mm)" if math.isfinite(noise) else ""))
            elif info < (1.0 + st.growth) * first:
                why = "pinned just now; counted once it has moved on a little more"
            elif not mine:
                why = "pinned; counted once a joint next to it is too (it ends no bone yet)"
            elif not covered or moved > st.within_m:
                why = (f"pinned; counted once its bones hold within {1000 * st.within_m:.0f} mm over "
                       f"{st.window_s:g} s" + (f" (moved {1000 * moved:.1f} mm)" if math.isfinite(moved) and covered else ""))
            else:
                continue
            it.update(state="settling", progress=SETTLING_SHARE, settling=why)

    def _hold(self, it: dict, pair: frozenset, j: dict | None, time_s: float, stale: bool) -> None:
        """A joint on its way to a stricter target than the tolerance shows the best share it has reached
        ("pinning"), so the ring does not follow its error's wobbles back either; a real loss resets it. As
        for done, the share counts once the joint has been determined for CONFIRM_S."""
        if it["state"] in ("pinning", "confirming"):
            since = self.pinning.setdefault(pair, float(time_s))
        else:
            since = None
            self.pinning.pop(pair, None)
        best = self.best.get(pair)
        if best is not None and j is not None and not j.get("determined"):
            if max(needed_errors(j, hinge=best["hinge"])) > LOSS_FACTOR * self.tolerance_m:
                del self.best[pair]
                self.undone[pair] = {"reason": "loss", "time_s": float(time_s), "sensor": it["joint"]}
                self.floor.pop(it["joint"], None)
                best = None
        held = since is not None and time_s - since >= self.confirm_s - 1e-9
        if it["state"] == "pinning" and held and not stale and (best is None or it["progress"] > best["value"]):
            best = self.best[pair] = {"value": it["progress"], "hinge": bool(j.get("hinge"))}
        # Kiosk: a joint pinned to its tolerance and waiting to hold still, or to count, shows that share.
        base = SETTLING_SHARE if self.steady is not None and it["state"] in ("settling", "confirming") else 0.0
        it["progress"] = max(best["value"] if best is not None else 0.0, base)

    def _hold_floor(self, items: list[dict]) -> None:
        """A sensor's share never falls but for a stated reason. Under soft tissue the tree re-links a
        joint between two neighbours that move almost as one (a thigh between pelvis and abdomen, back and
        forth): its best share is kept per pair, so each re-link showed the other pair's share and the ring
        went back (20 times in 8 guests) with no reason given. The share is held per sensor instead, and
        dropped only by a slip or a loss of fit (`slip`, LOSS_FACTOR), which the entry's `undone` names.
        A done joint the tree moves elsewhere is no longer done (its `undone` says "tree"): it shows just
        under 1 until it is done again."""
        for it in items:
            child = it["joint"]
            value = 1.0 if it["done"] else it["progress"]
            held = self.floor.get(child)
            if held is not None and value < held and not it["done"]:
                # A share below 1 is held as it was; a joint done once shows just under 1 (it is not done).
                it["progress"] = held if held < 1.0 else NOT_DONE_CAP
                it["held"] = True
                value = it["progress"]
            if held is None or value > held:
                self.floor[child] = value
                self._credited[child] = frozenset((child, it["parent"]))

    def _hold_ring(self, doc: dict, items: list[dict]) -> None:
        """The published figure goes down only for a reason an entry states (a slip, a loss, a re-link):
        in the first seconds the tree re-roots and a sensor that was the root joins the mean at 0, which
        took the ring back 5 times in 20 soft-tissue guests with nothing to say why."""
        floor = self._ring
        stated = any(it.get("undone") for it in items)
        if doc["progress"] < floor and not stated and not doc["done"]:
            doc["progress"] = floor
            doc["percent"] = int(math.floor(floor * 100 + 1e-9))
        self._ring = doc["progress"]

    def _stall(self, doc: dict, time_s: float) -> None:
        """`stalled_s` (how long the ring took to gain less than STALL_GAIN, once that is STALL_S or more)
        and a patient `prompt` naming the joint to move."""
        hist, lows = self._history, self._lows
        if doc["done"]:
            hist.clear()
            lows.clear()
            self._hist_gone = self._hist_n
        figure = doc["progress"]
        hist.append((time_s, figure))
        # An entry with a figure at or above this one can no longer be the newest low enough: drop it from
        # the search (at 30 fits a second a plateau held 80 s of history, scanned on every fit).
        while lows and lows[-1][2] >= figure:
            lows.pop()
        lows.append((self._hist_n, time_s, figure))
        self._hist_n += 1
        while len(hist) > 2 and hist[1][0] <= time_s - 10 * STALL_S:
            hist.popleft()
            self._hist_gone += 1
        while lows[0][0] < self._hist_gone:
            lows.popleft()
        # The newest entry whose figure is at least STALL_GAIN below this one, else the oldest kept.
        since = next((t for _, t, p in reversed(lows) if p <= figure - STALL_GAIN), hist[0][0])
        idle = time_s - since
        doc["stalled_s"] = round(idle, 1) if idle >= STALL_S and not doc["done"] else None
        doc["prompt"] = None
        if doc["stalled_s"] is not None and doc["missing"]:
            first = doc["missing"][0]
            doc["prompt"] = (f"Take your time and keep going: big, slow movements of your "
                             f"{joint_name(first['joint'], first.get('parent'))}, every way it bends.")

    def _carry_over(self, items: list[dict]) -> None:
        """Re-key done joints whose rigid group came apart: a joint done between bodies A and B (each a rigid
        group then) is the joint the tree now draws between a member of A and a member of B."""
        current = {frozenset((it["joint"], it["parent"])): it for it in items}
        for pair, it in current.items():
            if pair in self.latched:
                continue
            x, p = it["joint"], it["parent"]
            for old, latch in list(self.latched.items()):
                a, b = latch["bodies"]
                if old not in current and ((x in a and p in b) or (x in b and p in a)):
                    del self.latched[old]
                    self.latched[pair] = {**latch, "joint": x, "bodies": it["bodies"]}
                    break
