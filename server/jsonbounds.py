"""JSON from clients, parsed with a bound on nesting: deep nesting is refused with a readable reason.

Python's parser and every walk over the result recurse; a 30,000-level array would raise
RecursionError (a 500, a closed websocket) instead of a 4xx naming the problem.
"""

from __future__ import annotations

import json


def nesting_depth(value, limit: int) -> int:
    """Depth of nested lists/objects in `value` (a scalar is 0), counting no further than `limit` + 1."""
    depth, level = 0, [value] if isinstance(value, (list, dict)) else []
    while level and depth <= limit:
        depth += 1
        level = [x for v in level for x in (v.values() if isinstance(v, dict) else v) if isinstance(x, (list, dict))]
    return depth


def loads_bounded(text: str | bytes, max_depth: int, what: str = "the message") -> object:
    """`json.loads` that raises ValueError (never RecursionError) for bad JSON or nesting past `max_depth`."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise ValueError(f"{what} is nested too deeply (at most {max_depth} levels of lists/objects)") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{what} is not UTF-8 text ({exc.reason})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} is not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    if nesting_depth(value, max_depth) > max_depth:
        raise ValueError(f"{what} is nested too deeply (at most {max_depth} levels of lists/objects)")
    return value
