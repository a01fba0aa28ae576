"""The §5 JSON of a `Calibration` (docs/design.md §5), built here and only here, and read back from files.

`calibration_json` is what `flockcal fit --json`, `fit-markers --json`, the REST API and the exports
print; `calibration_from_json` is the one parser for a §5 object read from a file or a store, and
`as_calibration` what solver functions call on whatever calibration they are handed. The §5 object rounds
and leaves fields out: to store a result and rebuild it whole, solver/records.py.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from flockcal.solver.calibration import Bones, Calibration, HingePoints, OpticalExtras
from flockcal.solver.errors import SolverError
from flockcal.solver.fits import unfitted

if TYPE_CHECKING:
    from flockcal.solver.humanoid import Humanoid


# How a hinge's centre was placed on its axis (solver/hinge_point.py), by the number of limb bones used.
HINGE_POINT_RULES = {3: "bone_and_axis", 2: "two_bones", 1: "one_bone", 0: "min_norm"}


def calibration_json(cal) -> dict:
    """The docs/design.md §5 object of `cal`, with the extensions the solver emits.

    Every joint carries "determined" (docs/design.md §3a), "direction_error_m" (how closely the data pin
    the centre along its three least-turned directions, ascending; null where nothing turned) and
    "noise_error_m" (the part of that error more frames shrink: the classical, white-noise error), except
    in an optical fit, whose joints carry "kirk_rms_m" instead; a saved-skeleton fit adds "rms_free_m"
    and "known_skeleton"; a free fit adds "rigid_groups" (sensors that never turned relative to each
    other) and "ambiguous" (children with more than one equally good parent). Joints and bones refitted
    after a slip carry "segment_start_s"; a hinge says how its centre was placed on its axis, "hinge_point":
    {"rule" (`HINGE_POINT_RULES`: where the limb's bones meet the axis, or the minimum-norm point),
    "data_share" (the least-squares point's share in it)}. Every joint carries "name", as people name it
    (`Calibration.joint_names`); the object ends with "humanoid" ({sensor: VRM 1.0 bone}, or null with
    "humanoid_note" saying why) and "humanoid_conflicts" (sensors whose names say another bone than the one
    found: [{"sensor", "named", "found", "message"}]). NaN becomes null and every number is a Python int or float:
    the dict is valid JSON as it stands.
    """
    nm = cal.names
    j = cal.joints
    optical = cal.optical
    # Fields are converted together for all joints (the live server calls this ~30×/s), to Python
    # floats with None for NaN: the dict is JSON-safe as it stands, with no second pass over it.
    vec = _json(np.stack([j.c, j.l, j.axis_i, j.axis_j, j.coverage, j.direction_error, j.noise_error]))
    num = _json(np.stack([j.rms, j.epsilon, j.c_stderr, j.l_stderr]))
    sv = _json(j.singular_values)
    det = j.determined.tolist()
    free = None if cal.rms_free is None else _json(cal.rms_free)
    kirk = None if optical is None else _json(optical.kirk_rms)
    seg = None if cal.segment_start_s is None else _json(cal.segment_start_s)
    placed = None if cal.hinge_point is None else cal.hinge_point.rule.tolist()
    share = None if cal.hinge_point is None else cal.hinge_point.data_share.tolist()
    joint_names = cal.joint_names()
    joints = []
    for k, ((child, parent), hinge) in enumerate(zip(j.pairs.tolist(), j.hinge.tolist())):
        e = {"child": nm[child], "parent": nm[parent], "c": vec[0][k], "l": vec[1][k], "rms_m": num[0][k],
             "epsilon": num[1][k]}
        if free is not None:
            e["rms_free_m"] = free[k]
        e.update({
            "singular_values": sv[k],
            "hinge": hinge,
            "axis_child": vec[2][k] if hinge else None,
            "axis_parent": vec[3][k] if hinge else None,
            "coverage": vec[4][k],
            "c_stderr_m": num[2][k],
            "l_stderr_m": num[3][k],
        })
        if kirk is not None:
            e["kirk_rms_m"] = kirk[k]
            if optical.joint_decisions:
                e.update(optical.joint_decisions[k])
        else:
            e["determined"] = det[k]
            e["direction_error_m"] = vec[5][k]
            e["noise_error_m"] = vec[6][k]
        if seg is not None and seg[k] is not None:
            e["segment_start_s"] = seg[k]
        if hinge and placed is not None and placed[k] >= 0:
            e["hinge_point"] = {"rule": HINGE_POINT_RULES[placed[k]], "data_share": round(float(share[k]), 4)}
        e["name"] = joint_names[k]
        joints.append(e)
    bones = bones_json(cal.bones, nm)
    out = {
        "sensors": list(nm),
        "root": nm[cal.root],
        "parent": cal.parent_map(),
        "frames": int(cal.frames),
        "joints": joints,
        "bones": bones,
        "loop_candidates": [{"a": nm[a], "b": nm[bb], "rms_m": _num(r)} for a, bb, r in cal.loop_candidates],
        "slip_events": [_clean(event_json(e)) for e in cal.slip_events],
    }
    if optical is not None:
        out.update(bodies=dict(optical.bodies), markers=_clean(dict(optical.markers)),
                   unused_markers=list(optical.unused_markers), swap_events=[dict(e) for e in optical.swap_events],
                   marker_outlier_threshold_m=_clean(optical.marker_outlier_threshold_m), **_clean(dict(optical.exercise)))
    elif cal.known_skeleton:
        out["known_skeleton"] = True
    else:
        out["rigid_groups"] = [[nm[i] for i in g] for g in cal.rigid_groups]
        out["ambiguous"] = [{"child": nm[c], "parents": [nm[p] for p in ps], "note": note}
                            for c, ps, note in cal.ambiguous]
    out.update(humanoid_json(cal.humanoid, nm))
    return out


# What a fit made without a sample of the take's frames says in place of the humanoid.
NOT_LOOKED_FOR = "not looked for: the fit was given no frames of the take to find the humanoid from"


def humanoid_json(hum, names) -> dict:
    """The §5 extension keys of a `Humanoid` (or None: not looked for): "humanoid" {sensor: bone} or null,
    "humanoid_note" (only when null: why), "humanoid_conflicts" [{"sensor", "named", "found", "message"}]."""
    from flockcal.solver.humanoid import conflict_message

    if hum is None or not hum.human:
        return {"humanoid": None, "humanoid_note": NOT_LOOKED_FOR if hum is None else hum.reason,
                "humanoid_conflicts": []}
    return {"humanoid": hum.mapping(names),
            "humanoid_conflicts": [{"sensor": names[x.sensor], "named": x.named, "found": x.found,
                                    "message": conflict_message(names, x)} for x in hum.conflicts]}


def bones_json(b, names) -> list[dict]:
    """§5 `bones` entries of a `Bones` (sensor indices into `names`)."""
    length, stderr = _json(np.stack([b.length, b.stderr])) if len(b) else ([], [])
    seg = None if b.segment_start_s is None else _json(b.segment_start_s)
    out = []
    for k, (body, frm, to) in enumerate(zip(b.body.tolist(), b.from_joint.tolist(), b.to_joint.tolist())):
        e = {"body": names[body], "from_joint": names[frm] if frm >= 0 else None, "to_joint": names[to],
             "length_m": length[k], "stderr_m": stderr[k]}
        if seg is not None and seg[k] is not None:
            e["segment_start_s"] = seg[k]
        out.append(e)
    return out


def event_json(ev) -> dict:
    """A slip event as its §5 JSON entry: a SlipEvent/SwapEvent, a dict read from a file or store, or any
    object with the entry's fields as attributes (a stored event)."""
    if hasattr(ev, "to_dict"):
        return ev.to_dict()
    return dict(ev) if isinstance(ev, Mapping) else dict(vars(ev))


def event_from_json(d, names, error: type[Exception] = SolverError):
    """The `SlipEvent` (or `SwapEvent`) of a §5 `slip_events` entry read from a file or a store (its kind
    under "kind", or "type" as the service stores it); sensor indices from `names`, the take's sensors.
    Fields the entry lacks are NaN (numbers) or empty, and so are `joint_indices` (rows of the monitor's
    joint list, which no entry keeps); it must name a time and a sensor of `names`."""
    from flockcal.solver.slippage.monitor import SlipEvent, SwapEvent

    if not isinstance(d, Mapping):
        raise error(f"expected a slip event entry, got {type(d).__name__}")
    kind = d.get("kind", d.get("type", "slip"))
    if kind not in ("slip", "swap"):
        raise error(f"event of type {kind!r} is no slip or swap")
    names = [str(x) for x in names]
    try:
        time_s, sensor = float(d["time_s"]), str(d["sensor"])
        candidates = tuple(str(x) for x in d.get("candidates") or (sensor,))
        joints = tuple(str(x) for x in d.get("joints") or ())
        jump_mm, confidence, detected_s = (_or_nan(d.get(k)) for k in ("jump_mm", "confidence", "detected_s"))
        sensors = tuple(str(x) for x in d.get("sensors") or candidates) if kind == "swap" else (sensor,)
    except (KeyError, TypeError) as exc:
        raise error(f"slip event lacks {exc} (docs/design.md §5 lists the fields)") from None
    except ValueError as exc:
        raise error(f"slip event at {d.get('time_s')!r} s: {exc}") from None
    unknown = [x for x in sensors if x not in names]
    if unknown or len(sensors) != (2 if kind == "swap" else 1):
        raise error(f"slip event at {time_s} s names sensor(s) {', '.join(map(repr, unknown or sensors))}, "
                    f"not {'two' if kind == 'swap' else 'one'} of the take's")
    index = tuple(names.index(x) for x in sensors)
    if kind == "swap":
        return SwapEvent(time_s, *sensors, joints, jump_mm, confidence, detected_s, index)
    return SlipEvent(time_s, sensor, candidates, confidence, joints, jump_mm, detected_s, index[0])


def _or_nan(x) -> float:
    return float("nan") if x is None else float(x)


def _num(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _json(a) -> list:
    """An array as (nested) lists of Python floats, None where not finite: JSON has no NaN or infinity."""
    a = np.asarray(a, dtype=float)
    return np.where(np.isfinite(a), a, None).tolist()


def _clean(x):
    """Non-finite floats in nested lists and dicts as None."""
    if isinstance(x, float):
        return x if np.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def as_calibration(obj, names=None, error: type[Exception] = SolverError) -> Calibration:
    """`obj` as a Calibration: itself, a fit's `.calibration()` (saved-skeleton, optical), or a §5 dict
    parsed by `calibration_from_json` (`names`, `error` as there)."""
    if isinstance(obj, Calibration):
        return obj
    if callable(getattr(obj, "calibration", None)):
        return obj.calibration()
    return calibration_from_json(obj, names=names, error=error)


def calibration_from_json(d, names=None, error: type[Exception] = SolverError) -> Calibration:
    """A Calibration from a §5 object (`flockcal fit --json`, a skeleton file, a stored fit): the one parser.

    Reads the whole object `calibration_json` writes, so that `calibration_json(calibration_from_json(d))`
    is `d` again for any object it wrote: `sensors` (or the take's `names` when absent), `root`, `parent`
    (when absent: the joints' own child → parent), every tree joint's `c`, `l` and statistics, `bones`,
    `loop_candidates`, `slip_events` (as `SlipEvent` / `SwapEvent`), `rigid_groups`, `ambiguous`, a saved
    skeleton's and an optical fit's extra keys, and the humanoid. A field the object lacks reads as nothing
    measured (NaN, no hinge, nothing refitted after a slip); a joint without "determined" (a fit written
    before docs/design.md §3a, a truth file) counts as determined. Joints off the tree (loop candidates)
    are dropped; a null number becomes NaN. What the §5 object leaves out (the all-pair fits, covariances,
    a saved-skeleton fit's state) is not there to read: solver/records.py keeps a result whole. `error` is
    the exception the caller's users know; its message names the problem.
    """
    if not isinstance(d, Mapping):
        raise error(f"expected a Calibration or its §5 dict, got {type(d).__name__}")
    try:
        entries = list(d["joints"])
    except (KeyError, TypeError):
        raise error("the calibration has no 'joints' list (expected the `flockcal fit --json` shape)") from None
    try:
        if "sensors" in d:
            names = tuple(str(x) for x in d["sensors"])
        elif names is None:
            raise KeyError("'sensors'")
        else:
            names = tuple(str(x) for x in names)
        given = d.get("parent")
        parent_map = ({str(e["child"]): str(e["parent"]) for e in entries} if given is None
                      else {str(k): str(v) for k, v in dict(given).items()})
    except (KeyError, TypeError) as exc:
        raise error(f"calibration lacks {exc} (docs/design.md §5 lists the fields)") from None
    index = {x: i for i, x in enumerate(names)}
    unknown = sorted({x for kv in parent_map.items() for x in kv} - set(index))
    if unknown:
        raise error(f"the calibration names sensor(s) {', '.join(map(repr, unknown))}, which the take does not have")
    m = len(names)
    parent = np.full(m, -1, dtype=int)
    for child, par in parent_map.items():
        parent[index[child]] = index[par]
    roots = np.flatnonzero(parent < 0)
    root = d.get("root")
    if root is not None and str(root) in index and parent[index[str(root)]] != -1:
        raise error(f"root {root!r} has a parent in the parent map")
    root_i = index[str(root)] if root is not None and str(root) in index else int(roots[0]) if len(roots) else 0
    rows, tree = [], []
    for e in entries:
        child = str(e["child"])
        if child not in index:
            raise error(f"joint of unknown sensor {child!r}")
        i = index[child]
        if parent[i] < 0 or names[parent[i]] != str(e["parent"]):
            continue  # a non-tree joint (loop candidate) takes no part in driving the tree
        rows.append((i, int(parent[i])))
        tree.append(e)
    try:
        joints, extra = _joint_fits(rows, tree)
        bones = _bones_from_json(d.get("bones") or [], index)
        loops = [(index[str(x["a"])], index[str(x["b"])], _or_nan(x.get("rms_m"))) for x in d.get("loop_candidates") or []]
        groups = [[index[str(x)] for x in g if str(x) in index] for g in (d.get("rigid_groups") or [])]
        ambiguous = [(index[str(x["child"])], [index[str(p)] for p in x.get("parents") or []], str(x.get("note") or ""))
                     for x in d.get("ambiguous") or []]
    except KeyError as exc:
        raise error(f"the calibration names {exc} where a sensor or a field was expected (docs/design.md §5 "
                    "lists the fields)") from None
    except (TypeError, ValueError) as exc:
        raise error(f"the calibration has a malformed field ({exc}); docs/design.md §5 lists the fields") from None
    events = tuple(event_from_json(e, names, error) for e in d.get("slip_events") or [])
    placement = np.full((m, 3), np.nan)
    placement[joints.pairs[:, 0]] = joints.c
    humanoid = humanoid_from_json(d, names)
    order, k = [root_i], 0
    while k < len(order):  # root first, parents before children (a cycle stays out: callers check the tree)
        order += np.flatnonzero(parent == order[k]).tolist()
        k += 1
    return Calibration(names, root_i, parent, np.asarray(order), int(d.get("frames") or 0), joints, bones, placement,
                       loop_candidates=loops, rigid_groups=groups, ambiguous=ambiguous, hierarchy_given=True,
                       slip_events=events, known_skeleton=bool(d.get("known_skeleton")), humanoid=humanoid,
                       optical=_optical_from_json(d, extra) if "markers" in d else None, **extra["calibration"])


# The §5 keys a calibration's own fields fill; an optical fit's other top-level keys are its exercise report.
_KEYS = frozenset(("sensors", "root", "parent", "frames", "joints", "bones", "loop_candidates", "slip_events",
                   "bodies", "markers", "unused_markers", "swap_events", "marker_outlier_threshold_m", "known_skeleton",
                   "rigid_groups", "ambiguous", "humanoid", "humanoid_note", "humanoid_conflicts"))
_HINGE_RULES = {name: code for code, name in HINGE_POINT_RULES.items()}


def _joint_fits(rows: list, entries: list) -> tuple:
    """(PairFits of the tree joints' §5 entries, what else they carry: the Calibration's per-joint fields and an
    optical fit's per-joint keys)."""
    p = len(rows)
    joints = unfitted(rows)

    def num(key):
        return np.array([_or_nan(e.get(key)) for e in entries], dtype=float).reshape(p)

    def vec(key, k=3):
        return np.array([_vector(e.get(key), k) for e in entries], dtype=float).reshape(p, k)

    def present(key):
        return any(key in e for e in entries)

    joints = replace(
        joints, c=vec("c"), l=vec("l"), rms=num("rms_m"), epsilon=num("epsilon"), singular_values=vec("singular_values", 6),
        hinge=np.array([bool(e.get("hinge")) for e in entries], dtype=bool).reshape(p),
        determined=np.array([bool(e.get("determined", True)) for e in entries], dtype=bool).reshape(p),
        axis_i=vec("axis_child"), axis_j=vec("axis_parent"), coverage=vec("coverage"), c_stderr=num("c_stderr_m"),
        l_stderr=num("l_stderr_m"), direction_error=vec("direction_error_m"), noise_error=vec("noise_error_m"))
    own = {}
    if present("rms_free_m"):
        own["rms_free"] = num("rms_free_m")
    if present("segment_start_s"):
        own["segment_start_s"] = num("segment_start_s")
    if present("hinge_point"):
        placed = [e.get("hinge_point") or {} for e in entries]
        own["hinge_point"] = HingePoints(np.array([_HINGE_RULES[h["rule"]] if h else -1 for h in placed], dtype=int),
                                         np.array([float(h["data_share"]) if h else 0.0 for h in placed], dtype=float))
    optical = {}
    if present("kirk_rms_m"):
        optical["kirk_rms"] = num("kirk_rms_m")
        optical["joint_decisions"] = tuple({"determined": e.get("determined"), "direction_error_m": e.get("direction_error_m")}
                                           for e in entries)
    return joints, {"calibration": own, "optical": optical}


def _bones_from_json(entries: list, index: dict) -> Bones:
    """The `Bones` of §5 `bones` entries (a bone between two outboard joints of the root body names one of
    them as its `from_joint`, where every other bone names its own body's inboard joint: its body)."""
    body = np.array([index[str(b["body"])] for b in entries], dtype=int)
    frm = np.array([-1 if b.get("from_joint") is None else index[str(b["from_joint"])] for b in entries], dtype=int)
    to = np.array([index[str(b["to_joint"])] for b in entries], dtype=int)
    length = np.array([_or_nan(b.get("length_m")) for b in entries], dtype=float)
    stderr = np.array([_or_nan(b.get("stderr_m")) for b in entries], dtype=float)
    seg = (np.array([_or_nan(b.get("segment_start_s")) for b in entries], dtype=float)
           if any("segment_start_s" in b for b in entries) else None)
    return Bones(body, frm, to, length, stderr, (frm >= 0) & (frm != body), seg)


def _optical_from_json(d: Mapping, extra: dict) -> OpticalExtras:
    """An optical fit's extra keys (solver/optical/pipeline.py: "bodies", "markers", …) as its `OpticalExtras`."""
    got = extra["optical"]
    m = len(d["joints"])
    return OpticalExtras(got.get("kirk_rms", np.full(m, np.nan)), dict(d["bodies"]), dict(d.get("markers") or {}),
                         tuple(d.get("unused_markers") or ()), tuple(d.get("swap_events") or ()),
                         _or_nan(d.get("marker_outlier_threshold_m")), got.get("joint_decisions", ()),
                         {k: v for k, v in d.items() if k not in _KEYS})


def _vector(x, k: int) -> list:
    """A §5 vector of k numbers, NaN for a null entry or a null vector."""
    if x is None:
        return [np.nan] * k
    out = [np.nan if v is None else float(v) for v in x]
    if len(out) != k:
        raise ValueError(f"{out!r} is not {k} numbers")
    return out


def humanoid_from_json(d: Mapping, names) -> "Humanoid | None":
    """The humanoid a §5 object names ("humanoid": {sensor: bone}; its T-pose frames are not in the JSON,
    so they are NaN), a non-human one for null with its note, None when the object has no such key."""
    from flockcal.solver.humanoid import Humanoid, NameConflict, bones_of

    if "humanoid" not in d:
        return None
    m = len(names)
    nan = np.full((3, 3), np.nan)
    if not isinstance(d["humanoid"], Mapping):
        return Humanoid((None,) * m, nan, np.full((m, 3, 3), np.nan), str(d.get("humanoid_note") or "not human"))
    bones = bones_of(names, d["humanoid"])
    index = {x: i for i, x in enumerate(names)}
    conflicts = tuple(NameConflict(index[str(e["sensor"])], str(e["named"]), str(e["found"]))
                      for e in d.get("humanoid_conflicts") or [] if isinstance(e, Mapping) and str(e.get("sensor")) in index)
    return Humanoid(bones, nan, np.full((m, 3, 3), np.nan), "", conflicts)


