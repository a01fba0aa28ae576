"""Takes for the `flockcal batch` tests and benchmark: one simulated performer's routine cut into takes that
each exercise different joints, a C3D marker take, and how far a fit is from the simulation's truth.

The error measures are written from the truth alone (no solver code): a hinge's centre is compared only
across its axis, where the data can pin it; bones only between two ball joints, for the same reason.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flockcal.simulator.performer import Performer
from flockcal.takes import make_take, save_take

PERIOD_S = 60.0  # the exercise routine turns each group of joints in its own quarter of this loop
RATE_HZ = 100.0
SEED = 5


def performer(slip: tuple[str, float] | None = None) -> Performer:
    # Rigid sensors (sta_mm=0): the tests hold fits to the truth's rest placements, which soft tissue moves.
    p = Performer("human", "exercise", seed=SEED, sta_mm=0, rate_hz=RATE_HZ, period=PERIOD_S, seconds=PERIOD_S)
    if slip is not None:
        p.inject_slip(slip[0], 0.03, at_time=slip[1])
    return p


def routine_takes(folder: Path, parts: int = 3, slipped: dict | None = None, prefix: str = "part") -> tuple[list[Path], dict]:
    """The routine's loop cut into `parts` takes of PERIOD_S / parts each (files prefix0.npz …), and the
    truth. `slipped` {part: (sensor, absolute time s)}: that take comes from a performer whose sensor slid
    3 cm then (re-strapped before the next take, so only that take has the slip)."""
    clean = performer()
    paths = []
    n = int(round(PERIOD_S / parts * RATE_HZ))
    for k in range(parts):
        times = np.arange(n) / RATE_HZ + k * PERIOD_S / parts
        who = performer((slipped or {}).get(k)) if k in (slipped or {}) else clean
        R, t, v = who.poses(times)
        path = folder / f"{prefix}{k}.npz"
        save_take(path, make_take(R, t, clean.names, RATE_HZ, valid=v, times=times - times[0]))
        paths.append(path)
    return paths, clean.truth()


def write_c3d(path: Path, take) -> None:
    """A marker take as a C3D file in millimetres (what optical systems write); the calling test skips,
    saying why, without the optical extra."""
    ezc3d = pytest.importorskip("ezc3d", reason="writing C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [take.rate_hz]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.marker_names)
    pts = np.ones((4, take.n_markers, take.n_frames))
    pts[:3] = take.markers.transpose(2, 1, 0) * 1000.0
    c["data"]["points"] = pts
    c.add_parameter("POINT", "UNITS", ["mm"])
    c.write(str(path))


def _edges(d: dict) -> dict:
    """{frozenset(a, b): {a: point in a's frame, b: point in b's frame}}: joints whatever the root."""
    return {frozenset((j["child"], j["parent"])): {j["child"]: np.asarray(j["c"], float), j["parent"]: np.asarray(j["l"], float)}
            for j in d["joints"]}


def centre_errors(fit: dict, truth: dict) -> dict:
    """Per truth joint (child name), metres from the truth's centre, in both sensors' frames (the larger);
    hinges across their axis only; inf where the fitted tree lacks the joint."""
    fe = _edges(fit)
    out = {}
    for j in truth["joints"]:
        e = frozenset((j["child"], j["parent"]))
        if e not in fe:
            out[j["child"]] = np.inf
            continue
        worst = 0.0
        for body, true_point, axis in ((j["child"], j["c"], j["axis_child"]), (j["parent"], j["l"], j["axis_parent"])):
            d = fe[e][body] - np.asarray(true_point)
            if j["hinge"]:
                a = np.asarray(axis, float) / np.linalg.norm(axis)
                d = d - a * (a @ d)
            worst = max(worst, float(np.linalg.norm(d)))
        out[j["child"]] = worst
    return out


def _ball_bones(d: dict, hinge_edges: set) -> dict:
    """{(body, {its two neighbours}): length} for the fit's bones between two ball joints, whatever the root."""
    out = {}
    for b in d["bones"]:
        if b["from_joint"] is None:
            continue
        ends = [d["parent"][x] if x == b["body"] else x for x in (b["from_joint"], b["to_joint"])]
        if any(frozenset((b["body"], x)) in hinge_edges for x in ends):
            continue
        out[(b["body"], frozenset(ends))] = b["length_m"]
    return out


def bone_errors(fit: dict, truth: dict, keys=None) -> dict:
    """Metres from the true length, per bone between two ball joints that the fit drew (keyed by body and
    its two neighbours: the bones a tree draws depend on its root), or per bone of `keys` (inf where the
    fit drew none: an undetermined joint draws no bone)."""
    hinges = {frozenset((j["child"], j["parent"])) for j in truth["joints"] if j["hinge"]}
    points: dict[str, dict] = {}  # body → {neighbour: the joint's centre in the body's frame}
    for j in truth["joints"]:
        points.setdefault(j["child"], {})[j["parent"]] = np.asarray(j["c"], float)
        points.setdefault(j["parent"], {})[j["child"]] = np.asarray(j["l"], float)
    fb = _ball_bones(fit, hinges)
    out = {}
    for key in (fb if keys is None else keys):
        body, (a, b) = key[0], sorted(key[1])
        known = points.get(body, {})
        if key not in fb or a not in known or b not in known:  # not drawn, or between joints the body lacks
            out[key] = np.inf
            continue
        out[key] = abs(fb[key] - float(np.linalg.norm(known[a] - known[b])))
    return out
