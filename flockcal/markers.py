"""Optical marker takes: the marker .npz of docs/design.md §5 and C3D files (through ezc3d), validated.

A marker take is n frames of k labelled 3D points in metres, NaN where a marker was not seen. Every
problem found gets a one-line `MarkerError` that names the file and the fix.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.atomic import replacing
from flockcal.takes import read_npz, write_npz


class MarkerError(FlockcalError, ValueError):
    """A marker file that is missing, unreadable or inconsistent."""


@dataclass(frozen=True)
class MarkerTake:
    markers: np.ndarray  # (n, k, 3) float64 metres, NaN where unseen
    marker_names: tuple[str, ...]  # (k,)
    rate_hz: float
    times: np.ndarray  # (n,) seconds since start
    source: str = "markers"
    declared_frames: int | None = None  # frames a C3D header declares, when the file held fewer (--salvage)
    up: str | None = None  # the world's up axis the file states ("+z", "-z", "+y"), None when it states none
    up_from: str = ""  # where `up` comes from, for a person ("the C3D's POINT:Z_SCREEN", …)

    @property
    def n_frames(self) -> int:
        return self.markers.shape[0]

    @property
    def n_markers(self) -> int:
        return self.markers.shape[1]

    def visible(self) -> np.ndarray:
        """(n, k) True where a marker was seen."""
        return np.isfinite(self.markers).all(-1)


def make_marker_take(markers, marker_names, rate_hz, times=None, source: str = "markers", up: str | None = None,
                     up_from: str = "") -> MarkerTake:
    """Build a validated MarkerTake from arrays (metres); raises MarkerError naming the first problem."""
    M = np.asarray(markers, dtype=float)
    if M.ndim != 3 or M.shape[2] != 3:
        raise MarkerError(f"{source}: 'markers' must have shape (frames, markers, 3), got {M.shape}")
    n, k, _ = M.shape
    names = tuple(str(x) for x in np.atleast_1d(np.asarray(marker_names)).tolist())
    if len(names) != k:
        raise MarkerError(f"{source}: 'marker_names' has {len(names)} entries but 'markers' has {k} markers")
    if len(set(names)) != k:
        dup = sorted({x for x in names if names.count(x) > 1})
        raise MarkerError(f"{source}: marker names must be unique; repeated: {', '.join(dup)}")
    if n < 2:
        raise MarkerError(f"{source}: a marker take needs at least two frames, got {n}")
    if k < 2:
        raise MarkerError(f"{source}: a marker take needs at least two markers, got {k}")
    if np.isinf(M).any():
        raise MarkerError(f"{source}: 'markers' holds inf; write NaN for a marker that was not seen")
    # A point is seen or not: a partly-NaN point is not a position, so it counts as a gap.
    M = np.where(np.isfinite(M).all(-1, keepdims=True), M, np.nan)
    if not np.isfinite(M).any():
        raise MarkerError(f"{source}: no marker is seen in any frame")
    big = np.nanmax(np.abs(M))
    if big > 100.0:
        raise MarkerError(
            f"{source}: marker coordinates reach {big:.0f}, which is not metres; "
            "convert to metres (millimetres divide by 1000)"
        )
    rate = float(np.asarray(rate_hz))
    if not np.isfinite(rate) or rate <= 0:
        raise MarkerError(f"{source}: 'rate_hz' must be a positive number, got {rate_hz!r}")
    if times is None:
        ts = np.arange(n, dtype=float) / rate
    else:
        ts = np.asarray(times, dtype=float)
        if ts.shape != (n,) or not np.isfinite(ts).all():
            raise MarkerError(f"{source}: 'times' must be {n} finite numbers, got shape {ts.shape}")
        if np.any(np.diff(ts) < 0):
            raise MarkerError(f"{source}: 'times' must not go backwards")
    if up is not None and up not in UP_AXES:
        raise MarkerError(f"{source}: 'up' must be one of {', '.join(UP_AXES)}, got {up!r}")
    return MarkerTake(M, names, rate, ts, source, up=up, up_from=up_from if up is not None else "")


def is_marker_take(path) -> bool:
    """Whether `path` holds a marker take rather than a sensor take: a .c3d file, or an .npz with a
    `markers` array (a missing or unreadable file is left to the loader that reports it)."""
    import zipfile

    path = Path(path)
    if path.suffix.lower() == ".c3d":
        return True
    try:
        with zipfile.ZipFile(path) as z:
            return "markers.npy" in z.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def load_markers(path: str | os.PathLike, salvage: bool = False) -> MarkerTake:
    """Read a marker take from `.npz` (docs/design.md §5) or `.c3d`; raises MarkerError with the fix.
    `salvage` reads the frames a C3D cut short still holds instead of refusing it."""
    path = Path(path)
    if not path.exists():
        raise MarkerError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".c3d":
        return load_c3d(path, salvage=salvage)
    if suffix == ".npz":
        return load_marker_npz(path)
    raise MarkerError(f"{path}: unknown marker file type {suffix!r}; give a .c3d or a marker .npz")


def load_marker_npz(path: str | os.PathLike) -> MarkerTake:
    path = Path(path)
    arrays = read_npz(path, MarkerError, "marker takes come from np.savez or flockcal fit-markers")
    if "markers" not in arrays and "rotations" in arrays:
        raise MarkerError(f"{path}: this is a sensor take (rotations/positions); fit it with `flockcal fit`")
    missing = [k for k in ("markers", "marker_names", "rate_hz") if k not in arrays]
    if missing:
        raise MarkerError(f"{path}: missing array(s) {', '.join(missing)} (docs/design.md §5 lists what a marker take holds)")
    up = str(np.asarray(arrays["up"]).reshape(-1)[0]) if "up" in arrays else None
    return make_marker_take(arrays["markers"], arrays["marker_names"], arrays["rate_hz"], arrays.get("times"), str(path),
                            up=up, up_from="the file's 'up' entry")


def save_markers(path: str | os.PathLike, take: MarkerTake) -> None:
    """Write a marker take (atomically): a .c3d file for a name ending in .c3d (`save_c3d`), else the
    marker .npz of docs/design.md §5."""
    if Path(path).suffix.lower() == ".c3d":
        save_c3d(path, take)
        return
    write_npz(
        path,
        markers=take.markers,
        marker_names=np.asarray(take.marker_names, dtype=str),
        rate_hz=np.float64(take.rate_hz),
        times=take.times,
        **({} if take.up is None else {"up": np.asarray(take.up)}),
    )


_UNIT_SCALE = {"mm": 1e-3, "millimeters": 1e-3, "millimetres": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0, "metres": 1.0}
# Vicon and others store model outputs (angles, forces, …) as POINTs too; they are not markers.
_NOT_MARKERS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")


def _param(params, group, name, default=None):
    try:
        return params[group][name]["value"]
    except (KeyError, TypeError):
        return default


@dataclass(frozen=True)
class C3dLayout:
    """What a C3D file's own header says about its size: frames, bytes per frame, where the data start."""

    frames: int  # frames the header declares
    frame_bytes: int  # 3D points (4 values each) and analog samples of one frame
    data_start: int  # byte offset of the first frame
    size: int  # bytes in the file

    @property
    def held(self) -> int:
        """Whole frames the file holds."""
        return max(0, (self.size - self.data_start) // self.frame_bytes)


def c3d_layout(path: str | os.PathLike) -> C3dLayout | None:
    """The layout a C3D header declares, read from its first 512-byte block and the parameter section's
    processor byte (which fixes the byte order); None when the header cannot tell: not a C3D header,
    an unknown processor, or a count past the header's 16 bits (the true one is then only in the
    parameters)."""
    import struct

    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(512)
        if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
            return None
        fh.seek((head[0] - 1) * 512)
        section = fh.read(4)
    if len(section) < 4 or section[3] not in (84, 85, 86):  # Intel, DEC, MIPS
        return None
    big = section[3] == 86
    words = struct.unpack((">" if big else "<") + "12H", head[:24])
    points, analog, first, last, start_block = words[1], words[2], words[3], words[4], words[8]
    # The scale factor's sign says whether values are floats (4 bytes) or integers (2): IEEE floats keep
    # it in their last byte (first, big-endian), a DEC float in the high byte of its first word.
    scale = head[12:16]
    negative = bool((scale[0] if big else scale[1] if section[3] == 85 else scale[3]) & 0x80)
    frame_bytes = (4 * points + analog) * (4 if negative else 2)
    if last == 0xFFFF or last < first or start_block < 2 or frame_bytes == 0:
        return None
    return C3dLayout(last - first + 1, frame_bytes, (start_block - 1) * 512, size)


def ezc3d_module(doing: str):
    """The ezc3d module, or a MarkerError naming the extra that brings it (`doing`: "reading", "writing")."""
    try:
        import ezc3d
    except ImportError:
        raise MarkerError(f"{doing} C3D needs the ezc3d package: pip install 'flockcal[optical]'") from None
    return ezc3d


def save_c3d(path: str | os.PathLike, take: MarkerTake) -> None:
    """Write a marker take as a C3D file (through ezc3d), atomically: POINT:UNITS mm, the take's rate and
    marker names as labels, the take's up axis (if it states one) as POINT:Z_SCREEN, a marker not seen in a
    frame stored as C3D marks one (residual −1, at the origin), so `load_c3d` reads the take back as it was
    (to float32's precision)."""
    ezc3d = ezc3d_module("writing")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(take.rate_hz)]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.marker_names)
    c.add_parameter("POINT", "UNITS", ["mm"])
    if take.up is not None:  # the simulator's world is z down: a viewer (and `load_c3d`) reads it from here
        c.add_parameter("POINT", "Z_SCREEN", [take.up.upper()])
    xyz = take.markers.transpose(2, 1, 0) * 1000.0  # (3, k, n) mm
    seen = take.visible().T
    points = np.ones((4, take.n_markers, take.n_frames))
    points[:3] = np.where(seen, xyz, 0.0)
    c["data"]["points"] = points
    c["data"]["meta_points"] = {"residuals": np.where(seen, 0.0, -1.0)[None],
                                "camera_masks": np.zeros((7, *seen.shape), dtype=bool)}
    with replacing(path) as tmp:
        out = tmp.with_name(tmp.name + ".c3d")  # ezc3d adds .c3d to a name that lacks it
        try:
            c.write(str(out))
            os.replace(out, tmp)
        except RuntimeError as exc:  # ezc3d reports a failed write so
            raise OSError(str(exc)) from None
        finally:
            out.unlink(missing_ok=True)


def load_c3d(path: str | os.PathLike, salvage: bool = False) -> MarkerTake:
    """Markers of a C3D file in metres: model outputs dropped, invalid points (residual < 0, or exactly
    at the origin, which some writers use for 'not seen') set to NaN, unnamed points named P1…

    A file holding fewer frames than its header declares (cut short by a copy or a download) is
    refused with the count it holds, unless `salvage`: then those frames are read and the take's
    `declared_frames` says how many there should have been."""
    path = Path(path)
    ezc3d = ezc3d_module("reading")
    layout = c3d_layout(path)
    if layout is not None and layout.size < layout.data_start:
        raise MarkerError(f"{path}: the file ends at byte {layout.size}, before its marker data (from byte "
                          f"{layout.data_start}): it was cut short; copy it again")
    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises plain RuntimeError/IOError for a bad file
        raise MarkerError(f"{path}: not a readable C3D file ({exc})") from None
    params = c3d["parameters"]
    pts = np.asarray(c3d["data"]["points"], dtype=float)  # (4, k, n)
    # ezc3d reads what a cut file holds and says nothing (its copy of the header is rewritten to match);
    # its count is what decides, the header's layout what the file should have held.
    declared = None
    if layout is not None and pts.shape[2] < layout.frames:
        held = min(layout.held, pts.shape[2])
        if not salvage or held < 2:
            fix = f"; copy it again, or fit the {held} frames it holds with --salvage" if held >= 2 else "; copy it again"
            raise MarkerError(f"{path}: the file ends early: it holds {held} of the {layout.frames} frames its "
                              f"header declares (cut short by a copy or a download?){fix}")
        declared = layout.frames
        pts = pts[:, :, :held]
    k = pts.shape[1]
    if k == 0 or pts.shape[2] == 0:
        raise MarkerError(f"{path}: the C3D file holds no 3D points (analog-only?); nothing to fit")
    labels = []
    for name in ("LABELS", "LABELS2", "LABELS3", "LABELS4"):
        labels += [str(x).strip() for x in (_param(params, "POINT", name, []) or [])]
    labels = labels[:k] + [f"P{i + 1}" for i in range(len(labels), k)]
    labels = [lab if lab else f"P{i + 1}" for i, lab in enumerate(labels)]
    seen_names: dict[str, int] = {}
    for i, lab in enumerate(labels):  # C3D does not forbid repeated labels; make them unique
        if lab in seen_names:
            labels[i] = f"{lab}#{i + 1}"
        seen_names[lab] = i
    exclude = set()
    for group in _NOT_MARKERS:
        exclude |= {str(x).strip() for x in (_param(params, "POINT", group, []) or [])}
    units = str((_param(params, "POINT", "UNITS", ["mm"]) or ["mm"])[0]).strip().lower()
    if units not in _UNIT_SCALE:
        raise MarkerError(f"{path}: unknown POINT:UNITS {units!r}; expected mm, cm or m")
    rate = float(np.atleast_1d(_param(params, "POINT", "RATE", [0.0]))[0])
    xyz = pts[:3].transpose(2, 1, 0) * _UNIT_SCALE[units]  # (n, k, 3)
    try:
        res = np.asarray(c3d["data"]["meta_points"]["residuals"], dtype=float)[0].T[: xyz.shape[0]]  # (n, k)
        bad = res < 0
    except (KeyError, IndexError, TypeError):
        bad = np.zeros(xyz.shape[:2], dtype=bool)
    bad |= np.all(xyz == 0.0, axis=-1)
    xyz[bad] = np.nan
    keep = [i for i, lab in enumerate(labels) if lab not in exclude]
    if len(keep) < 2:
        raise MarkerError(f"{path}: fewer than two marker trajectories after dropping model outputs")
    up, up_from = c3d_up(params)
    take = make_marker_take(xyz[:, keep], [labels[i] for i in keep], rate, source=str(path), up=up, up_from=up_from)
    return take if declared is None else replace(take, declared_frames=declared)


# The up axes a take's world may have (flockcal.exports.bvh.UP_AXES draws them), as C3D's POINT:Z_SCREEN
# names them (the axis a viewer shows pointing up).
UP_AXES = ("+z", "-z", "+y")


def c3d_up(params) -> tuple[str, str]:
    """(up axis, where it comes from) of a C3D: its POINT:Z_SCREEN when that names an axis flockcal draws,
    else +z, the format's usual convention (Vicon, Qualisys and the C3D.org sample files are Z-up)."""
    screen = str((_param(params, "POINT", "Z_SCREEN", [""]) or [""])[0]).strip().lower()
    if screen in UP_AXES:
        return screen, "the C3D's POINT:Z_SCREEN"
    if screen:
        return "+z", f"the C3D convention (its POINT:Z_SCREEN {screen.upper()} is not drawn: give --up)"
    return "+z", "the C3D convention (the file has no POINT:Z_SCREEN)"
