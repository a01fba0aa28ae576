"""The solver's typed results as JSON without loss, and back: a `Calibration` (with its `PairFits`, `Bones`,
slip events, saved-skeleton state, …), a `SlipEvent` or a `SwapEvent`, for a store or a message that must
rebuild the object. The stable `flockcal fit --json` contract is another thing: solver/calibration_json.py.

Every field goes in, named as in its class; arrays keep dtype, shape and every bit; tuples, sets and
non-finite floats are tagged ("$tuple", "$frozenset", "$float"), so the text is strict JSON (no NaN).
"""

from __future__ import annotations

import dataclasses
import json
import math
from functools import cache

import numpy as np

from flockcal.solver.errors import SolverError

VERSION = 1
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


@cache
def _types() -> dict[str, type]:
    """The classes a record may hold, by name: nothing else is ever built from one."""
    from flockcal.solver.calibration import Bones, Calibration, HingePoints, OpticalExtras
    from flockcal.solver.fits import PairFits
    from flockcal.solver.humanoid import Humanoid, NameConflict
    from flockcal.solver.known_skeleton import KnownFit
    from flockcal.solver.reconstruct import Articulation
    from flockcal.solver.slippage.monitor import SlipEvent, SwapEvent

    return {t.__name__: t for t in (Calibration, Bones, HingePoints, OpticalExtras, PairFits, KnownFit,
                                    Articulation, SlipEvent, SwapEvent, Humanoid, NameConflict)}


def to_record(obj) -> dict:
    """`obj` (a Calibration, SlipEvent or SwapEvent) as a JSON-safe dict that `from_record` rebuilds."""
    return {"$record": VERSION, "value": _encode(obj)}


def from_record(record, expected: type | tuple[type, ...] | None = None, error: type[Exception] = SolverError):
    """The object `to_record` was given, rebuilt from its record (a dict, or its JSON text); `expected`:
    the class (or classes) it must be. A record that is not one raises `error` naming what is wrong."""
    if isinstance(record, (str, bytes)):
        try:
            record = json.loads(record)
        except ValueError as exc:
            raise error(f"the record is not JSON ({exc})") from None
    if not isinstance(record, dict) or "$record" not in record:
        raise error("not a flockcal record (expected the dict of solver.records.to_record)")
    if record["$record"] != VERSION:
        raise error(f"record version {record['$record']!r}; this flockcal reads version {VERSION}")
    try:
        obj = _decode(record["value"])
    except (KeyError, TypeError, ValueError) as exc:
        raise error(f"the record is damaged: {exc}") from None
    if expected is not None and not isinstance(obj, expected):
        wanted = expected if isinstance(expected, tuple) else (expected,)
        raise error(f"the record holds a {type(obj).__name__}, not a {' or '.join(t.__name__ for t in wanted)}")
    return obj


def record_text(obj) -> str:
    """`to_record(obj)` as JSON text (strict: no NaN or Infinity tokens)."""
    return json.dumps(to_record(obj), allow_nan=False, separators=(",", ":"))


def _encode(x):
    if x is None or isinstance(x, (bool, str)):
        return x
    if isinstance(x, (int, np.integer)) and not isinstance(x, np.bool_):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else {"$float": repr(x)}
    if isinstance(x, np.ndarray):
        return _array(x)
    if isinstance(x, list):
        return [_encode(v) for v in x]
    if isinstance(x, tuple):
        return {"$tuple": [_encode(v) for v in x]}
    if isinstance(x, (set, frozenset)):
        items = sorted((_encode(v) for v in x), key=lambda v: json.dumps(v, sort_keys=True))
        return {"$frozenset" if isinstance(x, frozenset) else "$set": items}
    if isinstance(x, dict):
        if all(isinstance(k, str) and not k.startswith("$") for k in x):
            return {k: _encode(v) for k, v in x.items()}
        return {"$dict": [[_encode(k), _encode(v)] for k, v in x.items()]}
    name = type(x).__name__
    if dataclasses.is_dataclass(x) and _types().get(name) is type(x):
        return {"$type": name, **{f.name: _encode(getattr(x, f.name)) for f in dataclasses.fields(x)}}
    raise SolverError(f"a record cannot hold a {name}")


def _array(a: np.ndarray) -> dict:
    if a.dtype.kind not in "biuf":
        raise SolverError(f"a record cannot hold an array of dtype {a.dtype}")
    data = a.astype(object)
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a)
        if bad.any():  # strings in a float array: numpy reads "nan", "inf", "-inf" back as those floats
            data[bad] = np.where(np.isnan(a[bad]), "nan", np.where(a[bad] > 0, "inf", "-inf"))
    return {"$array": a.dtype.name, "shape": list(a.shape), "data": data.tolist()}


def _decode(x):
    if isinstance(x, list):
        return [_decode(v) for v in x]
    if not isinstance(x, dict):
        return x
    if "$type" in x:
        cls = _types().get(x["$type"])
        if cls is None:
            raise ValueError(f"unknown type {x['$type']!r}")
        return cls(**{k: _decode(v) for k, v in x.items() if k != "$type"})
    if "$array" in x:
        dtype = np.dtype(x["$array"])
        if dtype.kind not in "biuf":
            raise ValueError(f"array dtype {dtype}")
        return np.array(x["data"], dtype=dtype).reshape(x["shape"])
    if "$float" in x:
        return _NON_FINITE[x["$float"]]
    if "$tuple" in x:
        return tuple(_decode(v) for v in x["$tuple"])
    if "$frozenset" in x:
        return frozenset(_decode(v) for v in x["$frozenset"])
    if "$set" in x:
        return {_decode(v) for v in x["$set"]}
    if "$dict" in x:
        return {_decode(k): _decode(v) for k, v in x["$dict"]}
    return {k: _decode(v) for k, v in x.items()}
