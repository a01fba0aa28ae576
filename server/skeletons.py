"""Saved skeletons the service can start a session with, and fitting a session with one.

A `SkeletonLibrary` holds skeleton files (flockcal.exports.skeleton) checked against the tracker's
sensor names: uploads live in DATA_DIR/skeletons/NAME.json, `--skeleton FILE`s are read at start.
`known_fit` fits a session's accumulator with a saved skeleton (bones fixed, placements free).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flockcal.atomic import write_atomic
from flockcal.errors import FlockcalError
from flockcal.server.errors import BadRequest, Conflict, NotFound
from flockcal.server.settings import NAME_RE

log = logging.getLogger(__name__)

# Preset names the service gives meaning to itself; a saved skeleton cannot take them.
RESERVED = ("auto", "human")
MAX_DEPTH = 8  # a skeleton file nests 4 deep (joints → joint → c → number); deeper is not one


@dataclass(frozen=True)
class Entry:
    name: str
    skeleton: object  # flockcal.exports.skeleton.Skeleton
    origin: str  # "upload" (stored in the data dir) or the --skeleton file's path

    def summary(self) -> dict:
        data = self.skeleton.data
        source = data.get("source") if isinstance(data.get("source"), dict) else {}
        return {"name": self.name, "performer": performer_of(data), "root": self.skeleton.root,
                "sensors": list(self.skeleton.names), "hierarchy": self.skeleton.hierarchy,
                "bones": len(data.get("bones", [])), "origin": self.origin, "source": source,
                "created_utc": data.get("created_utc")}


def performer_of(data: dict) -> str | None:
    """The performer a skeleton file names (top level or its `source`), if any."""
    source = data.get("source") if isinstance(data.get("source"), dict) else {}
    name = data.get("performer") or source.get("performer")
    return name if isinstance(name, str) and name.strip() else None


def safe_name(text: str) -> str | None:
    """`text` made a preset name (letters, digits, space _ . -, 1–64, starting alphanumeric), or None."""
    name = re.sub(r"[^A-Za-z0-9 _.\-]", "_", text.strip())[:64].strip()
    name = name.lstrip(" _.-")
    return name if name and NAME_RE.fullmatch(name) else None


def check_performers(data: dict) -> None:
    """BadRequest unless every performer the file names (top level, `source`) is a valid performer name:
    it is shown in the preset list and may become a session's performer."""
    from flockcal.server.settings import PERFORMER_RE, PERFORMER_RULE

    source = data.get("source") if isinstance(data.get("source"), dict) else {}
    for where, value in (("performer", data.get("performer")), ("source.performer", source.get("performer"))):
        if value is None:
            continue
        if not isinstance(value, str) or not PERFORMER_RE.fullmatch(value) or not value.strip():
            raise BadRequest(f"the skeleton's {where} {str(value)[:80]!r} is not allowed: a performer name is "
                             f"{PERFORMER_RULE}; fix it in the file")


class SkeletonLibrary:
    """Named skeletons for the tracker's `names`. Readers see a dict that is replaced, never changed,
    so API threads can list while another uploads."""

    def __init__(self, directory: Path, names: tuple[str, ...]):
        self.directory = Path(directory)
        self.names = tuple(names)
        self._entries: dict[str, Entry] = {}
        self._lock = threading.Lock()  # one upload or delete at a time
        self._load_stored()

    def _load_stored(self) -> None:
        from flockcal.exports.skeleton import load_skeleton

        if not self.directory.is_dir():
            return
        for path in sorted(self.directory.glob("*.json")):
            name = path.stem
            try:
                skel = load_skeleton(path)
                skel.check_names(self.names)
            except FlockcalError as exc:
                # A stored file for another sensor set (the tracker changed) stays on disk, unused.
                log.warning("stored skeleton %s not loaded: %s", path.name, exc)
                continue
            if NAME_RE.fullmatch(name) and name not in RESERVED:
                self._entries = {**self._entries, name: Entry(name, skel, "upload")}

    # --- reading -------------------------------------------------------------------------------------
    def get(self, name: str):
        entry = self._entries.get(name)
        return entry.skeleton if entry else None

    def list(self) -> list[dict]:
        return [e.summary() for e in sorted(self._entries.values(), key=lambda e: e.name.lower())]

    def hierarchies(self) -> dict[str, dict]:
        return {name: e.skeleton.hierarchy for name, e in self._entries.items()}

    # --- adding --------------------------------------------------------------------------------------
    def _check(self, skel, origin: str) -> None:
        from flockcal.exports.skeleton import SkeletonError

        ours, theirs = set(self.names), set(skel.names)
        if ours != theirs:
            unknown = sorted(theirs - ours)
            missing = sorted(ours - theirs)
            parts = []
            if unknown:
                parts.append(f"unknown sensor(s) {', '.join(unknown)}")
            if missing:
                parts.append(f"missing sensor(s) {', '.join(missing)}")
            raise SkeletonError(f"{origin} does not match the tracker: {'; '.join(parts)} "
                                f"(the tracker's sensors are {', '.join(self.names)})")
        skel.check_names(self.names)

    def load_file(self, path: str | os.PathLike) -> str:
        """A `--skeleton FILE`: validate, check against the sensors, name it; SkeletonError otherwise."""
        from flockcal.exports.skeleton import SkeletonError, load_skeleton

        path = Path(path)
        skel = load_skeleton(path)
        self._check(skel, str(path))
        name = safe_name(performer_of(skel.data) or "") or safe_name(path.stem)
        if name is None:
            raise SkeletonError(f"{path}: cannot make a preset name from it; rename the file (letters, digits, _ . -)")
        if name in RESERVED:
            raise SkeletonError(f"{path}: the name {name!r} is reserved; rename the file or the performer")
        if name in self._entries and self._entries[name].origin != "upload":
            raise SkeletonError(f"{path}: a skeleton named {name!r} is already loaded from "
                                f"{self._entries[name].origin}; give each performer's file once")
        self._entries = {**self._entries, name: Entry(name, skel, str(path))}
        return name

    def upload(self, body: bytes, name: str | None = None, replace: bool = False) -> dict:
        """Store an uploaded skeleton (JSON bytes) under `name` (default: its performer) → its summary.

        BadRequest for a malformed or mismatched file, Conflict for a taken name; nothing is written then."""
        from flockcal.exports.skeleton import SkeletonError, parse_skeleton

        from flockcal.server.jsonbounds import loads_bounded

        try:
            data = loads_bounded(body, MAX_DEPTH, "the uploaded skeleton")
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        try:
            skel = parse_skeleton(data, origin="uploaded skeleton")
            self._check(skel, "uploaded skeleton")
        except SkeletonError as exc:
            raise BadRequest(str(exc)) from None
        check_performers(skel.data)
        if name is None:
            name = safe_name(performer_of(skel.data) or "")
            if name is None:
                raise BadRequest("the skeleton names no performer; give one as ?name=")
        elif not NAME_RE.fullmatch(name):
            raise BadRequest("skeleton name must be 1–64 of letters, digits, space, _ . - (starting with a letter or digit)")
        if name in RESERVED:
            raise BadRequest(f"the name {name!r} is reserved; choose another with ?name=")
        with self._lock:
            return self._store(skel, name, replace)

    def _store(self, skel, name: str, replace: bool) -> dict:
        old = self._entries.get(name)
        if old is not None and old.origin != "upload":
            raise Conflict(f"skeleton {name!r} comes from {old.origin} (--skeleton); choose another ?name=")
        if old is not None and not replace:
            raise Conflict(f"a skeleton named {name!r} exists; add ?replace=true to overwrite it or choose another ?name=")
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"{name}.json"
        write_atomic(path, json.dumps(skel.data, indent=1) + "\n")
        entry = Entry(name, skel, "upload")
        self._entries = {**self._entries, name: entry}
        return entry.summary()

    def delete(self, name: str) -> None:
        with self._lock:
            self._delete(name)

    def _delete(self, name: str) -> None:
        entry = self._entries.get(name)
        if entry is None:
            raise NotFound(f"no skeleton {name!r}; GET /api/skeletons lists them")
        if entry.origin != "upload":
            raise Conflict(f"skeleton {name!r} comes from {entry.origin} (--skeleton); restart without it instead")
        (self.directory / f"{name}.json").unlink(missing_ok=True)
        self._entries = {k: v for k, v in self._entries.items() if k != name}


# --- fitting a session with a saved skeleton ---------------------------------------------------------
class SegmentView:
    """A SegmentedAccumulator seen as one GramAccumulator whose pair statistics come from each pair's
    segment (after a slip: the frames since it), so a known-skeleton fit refits a slipped sensor's
    joints on its new placement while the saved bones stay as they are."""

    def __init__(self, seg):
        self._seg = seg
        self.whole = seg.whole

    def __getattr__(self, name):
        return getattr(self.whole, name)

    def _grouped(self, pairs, method: str):
        P = np.asarray(pairs, dtype=int).reshape(-1, 2)
        segs = self._seg.pair_segments(P)
        groups: dict[int, list[int]] = {}
        keyed = {}
        for k, s in enumerate(segs):
            groups.setdefault(id(s), []).append(k)
            keyed[id(s)] = s
        out = None
        for key, rows in groups.items():
            s = keyed[key]
            acc = self.whole if s is None else self._seg._segment_acc(s)
            part = getattr(acc, method)(P[rows])
            single = not isinstance(part, tuple)
            parts = (part,) if single else part
            if out is None:
                out = [np.empty((len(P),) + np.shape(x)[1:], dtype=np.result_type(x)) for x in parts]
            for o, x in zip(out, parts):
                o[rows] = x
        if out is None:
            return getattr(self.whole, method)(P)
        return out[0] if len(out) == 1 and method == "translation_power" else tuple(out)

    def normal_equations(self, pairs):
        return self._grouped(pairs, "normal_equations")

    def translation_power(self, pairs):
        return self._grouped(pairs, "translation_power")

    def block_moments(self, pairs):
        return self._grouped(pairs, "block_moments")


def saved_placement(skeleton, names):
    """A stand-in previous fit that starts the Gauss–Newton at the saved placements themselves."""
    from flockcal.solver.known_skeleton import KnownFit

    art = skeleton.articulation.reordered(list(names))
    m = art.n_bodies
    nan = np.full(m, np.nan)
    return KnownFit(art, 0, nan, nan, nan, 0, motion=(np.broadcast_to(np.eye(3), (m, 3, 3)).copy(), np.zeros((m, 3))))


def known_fit(skeleton, acc, names, previous=None):
    """`skeleton.fit` on a session's accumulator (a SegmentedAccumulator is seen through SegmentView).

    A cold fit tries two starts and keeps the better: the solver's own (each body's saved points moved
    onto the free joint fits) and the saved placements as they are. On a tie — a body whose joints have
    not moved yet, so the data cannot place it — the saved placement wins instead of an arbitrary one:
    early in a take the unexercised limbs stay where the performer's file put them."""
    view = SegmentView(acc) if hasattr(acc, "whole") and getattr(acc, "segments", None) else getattr(acc, "whole", acc)
    names = list(names)
    if previous is not None:
        return skeleton.fit(view, names, previous=previous)
    anchored = skeleton.fit(view, names, previous=saved_placement(skeleton, names))
    free = skeleton.fit(view, names)
    cost_anchored, cost_free = (float(np.nansum(f.rms ** 2)) for f in (anchored, free))
    return anchored if cost_anchored <= cost_free * (1 + 1e-6) + 1e-12 else free


def known_dict(fit, acc, names) -> dict:
    """The §5 dict of a KnownFit, joints refitted on a segment marked `segment_start_s` as in free fits."""
    d = fit.to_dict()
    segments = getattr(acc, "segments", None)
    if segments:
        index = {n: i for i, n in enumerate(names)}
        for entry in d["joints"]:
            seg = acc.pair_segments([(index[entry["child"]], index[entry["parent"]])])[0]
            if seg is not None:
                entry["segment_start_s"] = seg.start_s
    return d
