"""TRC (track-row-column text) of a take's joint centres: each joint of the fitted tree a virtual marker,
in millimetres, laid out as OpenSim's TRCFileAdapter reads it, so OpenSim's Scale and IK tools can use
functional joint centres. Written a chunk of frames at a time (`trc_chunks`), as the BVH is.
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from flockcal.atomic import write_pieces
from flockcal.errors import FlockcalError
from flockcal.exports.bvh import bvh_world
from flockcal.solver.reconstruct import Articulation, articulation
from flockcal.takes import ChunkedTake

MM_PER_M = 1000.0
POSITION_DECIMALS = 3  # 1 µm: far below the tracker's noise, and the file stays about 30 bytes a marker-frame
TIME_DECIMALS = 6


class TrcError(FlockcalError, ValueError):
    """A TRC that cannot be written as asked (a calibration with no joints)."""


@dataclass(frozen=True)
class JointMarkers:
    """The markers of a calibration in a take's sensor order: marker k is the joint between sensors
    `child[k]` and `parent[k]`, at `c[k]` in the child's sensor frame and `l[k]` in the parent's."""

    names: list[str]
    child: np.ndarray
    parent: np.ndarray
    c: np.ndarray
    l: np.ndarray


def marker_name(joint: str) -> str:
    """A joint's name as a marker label: 'left knee' → 'left_knee' (letters, digits and _ only, since TRC
    readers split on tabs and some on any whitespace)."""
    return re.sub(r"[^A-Za-z0-9]+", "_", str(joint)).strip("_") or "joint"


def joint_markers(calibration, names) -> JointMarkers:
    """One marker per joint of the fitted tree (a sensor riding rigidly on its parent has no joint, so no
    marker), in the fit's joint order, for a take whose sensors are `names`. A joint is labelled by its
    `name` in the fit JSON when the fit gives one, else as flockcal names joints (flockcal.names.joint_name)."""
    from flockcal.names import joint_name

    art = calibration if isinstance(calibration, Articulation) else articulation(calibration)
    art = art.reordered(names)
    data = {} if isinstance(calibration, Articulation) else (
        calibration if isinstance(calibration, dict) else calibration.to_dict())
    tree = data.get("parent", {})
    named = {str(j["child"]): j.get("name") for j in data.get("joints", [])
             if isinstance(j, dict) and tree.get(j.get("child")) == j.get("parent")}  # not a loop candidate
    rigid = art.rigid if art.rigid is not None else np.zeros(art.n_bodies, dtype=bool)
    order = [art.names.index(n) for n in named if n in art.names] or list(art.order)
    child = np.array([j for j in order if art.parent[j] >= 0 and not rigid[j]], dtype=int)
    if not len(child):
        raise TrcError("the calibration has no fitted joint to write as a marker")
    labels: list[str] = []
    for j in child:
        text = named.get(art.names[j]) or joint_name(art.names[j], art.names[art.parent[j]])
        label, k = marker_name(text), 1
        while label in labels:
            k += 1
            label = f"{marker_name(text)}_{k}"
        labels.append(label)
    return JointMarkers(labels, child, art.parent[child], art.c[child], art.l[child])


def marker_positions(markers: JointMarkers, rotations, positions, valid=None) -> np.ndarray:
    """(n, k, 3) each marker in tracker-world metres: the midpoint of the two sensors' copies of the joint,
    R_child c + t_child and R_parent l + t_parent (they differ by the joint's residual); NaN at a frame where
    either sensor is invalid."""
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    a = np.einsum("nkab,kb->nka", R[:, markers.child], markers.c) + t[:, markers.child]
    b = np.einsum("nkab,kb->nka", R[:, markers.parent], markers.l) + t[:, markers.parent]
    out = 0.5 * (a + b)
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        out[~(v[:, markers.child] & v[:, markers.parent])] = np.nan
    return out


def trc_times(take: ChunkedTake) -> bool:
    """True when the take's clock, as the file writes it, strictly increases (OpenSim refuses a time that
    does not); else the file's Time is frame / rate. Read a chunk at a time."""
    last, t0 = -np.inf, None
    for f in take.chunks():
        if not len(f.times):
            continue
        t0 = f.times[0] if t0 is None else t0
        t = np.round(np.asarray(f.times, dtype=float) - t0, TIME_DECIMALS)
        if not (np.diff(np.r_[last, t]) > 0).all():
            return False
        last = t[-1]
    return True


def trc_chunks(calibration, take: ChunkedTake, *, up: str = "-z", file_name: str = "take.trc",
               chunk_frames: int | None = None) -> Iterator[str]:
    """The TRC of `take` (a Take, or any ChunkedTake: the service's frame log) through `calibration` (a
    Calibration, a KnownFit, a §5 dict or an Articulation), as text: the five header lines and a blank one,
    then the rows of `chunk_frames` frames at a time. Axes: the tracker world turned Y-up by `up` (as the
    BVH's); millimetres. A missing marker is three empty fields, every row ending in a tab as OpenSim's
    own writer ends them. Errors in the calibration or the take come from the first next()."""
    world = bvh_world(up)
    markers = joint_markers(calibration, take.names)
    own_clock = trc_times(take)
    n, k, rate = int(take.n_frames), len(markers.names), float(take.rate_hz)
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate:.10g}\t{rate:.10g}\t{n}\t{k}\tmm\t{rate:.10g}\t1\t{n}",
        "Frame#\tTime\t" + "".join(f"{name}\t\t\t" for name in markers.names),
        "\t\t" + "".join(f"X{i}\tY{i}\tZ{i}\t" for i in range(1, k + 1)),
        "",
    ]
    yield "\n".join(head) + "\n"
    fmt = "\t".join(["%d", f"%.{TIME_DECIMALS}f"] + [f"%.{POSITION_DECIMALS}f"] * (3 * k))
    at, t0 = 0, None
    for f in take.chunks(chunk_frames):
        m = len(f.times)
        if not m:
            continue
        t0 = f.times[0] if t0 is None else t0
        times = np.asarray(f.times, dtype=float) - t0 if own_clock else (at + np.arange(m)) / rate
        xyz = marker_positions(markers, f.rotations, f.positions, f.valid) @ world.T * MM_PER_M
        rows = np.column_stack([at + 1 + np.arange(m), times, xyz.reshape(m, -1)])
        out = io.StringIO()
        np.savetxt(out, rows, fmt=fmt, newline="\t\n")
        yield out.getvalue().replace("nan", "")  # a missing marker: empty fields, as TRC readers expect
        at += m


def trc_text(calibration, take, **options) -> str:
    """The whole TRC file as one string (`trc_chunks` joined)."""
    return "".join(trc_chunks(calibration, take, **options))


def write_trc(path: str | os.PathLike, calibration, take, **options) -> None:
    """Write the TRC to `path` a chunk of frames at a time (atomically: a failure never leaves a
    half-written file)."""
    options.setdefault("file_name", Path(path).name)
    write_pieces(path, trc_chunks(calibration, take, **options), encoding="utf-8")
