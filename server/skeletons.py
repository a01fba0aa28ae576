"""Saved skeletons the service can start a session with, and fitting a session with one.

A `SkeletonLibrary` holds skeleton files (flockcal.exports.skeleton) checked against the tracker's
sensor names: uploads live in DATA_DIR/skeletons/NAME.json, `--skeleton FILE`s are read at start.
Fitting a session with one is the solver's (flockcal.solver.solve).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path


from flockcal.atomic import write_atomic
from flockcal.errors import FlockcalError
from flockcal.server.errors import BadRequest, Conflict, NotFound, ServerError
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
        skel = self.skeleton
        return {"name": self.name, "performer": skel.performer, "root": skel.root, "sensors": list(skel.names),
                "hierarchy": skel.hierarchy, "bones": skel.bone_count, "origin": self.origin, "source": skel.source,
                "created_utc": skel.created_utc}


def safe_name(text: str) -> str | None:
    """`text` made a preset name (letters, digits, space _ . -, 1–64, starting alphanumeric), or None."""
    name = re.sub(r"[^A-Za-z0-9 _.\-]", "_", text.strip())[:64].strip()
    name = name.lstrip(" _.-")
    return name if name and NAME_RE.fullmatch(name) else None


def check_performers(skel) -> None:
    """BadRequest unless every performer the skeleton file names (top level, `source`) is a valid performer
    name: it is shown in the preset list and may become a session's performer."""
    from flockcal.server.settings import PERFORMER_RE, PERFORMER_RULE

    for where, value in skel.performers:
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
            except Exception as exc:  # a damaged file must not keep the service from starting
                log.warning("stored skeleton %s not loaded: it cannot be read as a skeleton (%s: %s); it stays "
                            "on disk, unused", path.name, type(exc).__name__, str(exc)[:200])
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
        name = safe_name(skel.performer or "") or safe_name(path.stem)
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
        from flockcal.skeleton import SkeletonRangeError

        from flockcal.server.jsonbounds import loads_bounded

        try:
            data = loads_bounded(body, MAX_DEPTH, "the uploaded skeleton")
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        try:
            skel = parse_skeleton(data, origin="uploaded skeleton")
            self._check(skel, "uploaded skeleton")
        except SkeletonRangeError as exc:  # a number out of range, as for any request: 422
            raise ServerError(str(exc), status=422, code="invalid_request") from None
        except SkeletonError as exc:
            raise BadRequest(str(exc)) from None
        check_performers(skel)
        if name is None:
            name = safe_name(skel.performer or "")
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
