"""One clock (docs/internals.md, "Clock"): the driver, the simulator and the service read the time only from
the clock handed to them (`flockcal.clock.Clock`), never from the machine's clocks directly, so a test can run
them on a `ManualClock` and a stepped wall clock moves nothing it should not.

Statically, over the syntax tree of every module of drivers/, simulator/ and server/: no call of (or reference
to) `time.time`, `time.monotonic`, `time.perf_counter`, `time.clock_gettime`, `time.sleep` and their `_ns`
kin, `datetime.now`/`utcnow`/`today`, `date.today`, or `time.localtime()` and its kin asked for *now* (with a
stamp to format they read no clock); and the machine's clock object `SYSTEM` only where the service or the
driver is built (the one default at the top). The clock modules themselves (flockcal/clock.py, server/clock.py)
are where the machine's clocks are read.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("drivers", "simulator", "server")
CLOCK_MODULES = {"server/clock.py"}
# The machine's clock is a parameter's default (what a caller who gives none gets: the command line, a
# library user) and nothing else, but where a sim:// port is opened by its URL alone (pyserial passes no clock).
SYSTEM_NAMED = {"simulator/protocol_sim.py"}
# Reads not yet moved onto the clock, counted exactly so that none is added and an entry goes with its last
# read (none left: the frame log's flush cadence was the last, now on the session's clock).
PENDING: dict[str, int] = {}

TIME_READERS = {"time", "time_ns", "monotonic", "monotonic_ns", "perf_counter", "perf_counter_ns",
                "clock_gettime", "clock_gettime_ns", "sleep"}
DATETIME_NOW = {"now", "utcnow", "today"}
# These read the clock only when not given a time (strftime's format is its first argument).
NOW_BY_DEFAULT = {"localtime": 0, "gmtime": 0, "ctime": 0, "asctime": 0, "strftime": 1}


def clock_reads(source: str) -> list[tuple[int, str]]:
    """(line, what) of every direct read of the machine's clocks in `source`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module == "time":
            found += [(node.lineno, f"from time import {a.name}") for a in node.names if a.name in TIME_READERS]
        elif isinstance(node, ast.Attribute):
            base = node.value
            name = base.id if isinstance(base, ast.Name) else base.attr if isinstance(base, ast.Attribute) else None
            if name == "time" and node.attr in TIME_READERS:
                found.append((node.lineno, f"time.{node.attr}"))
            elif name in ("datetime", "date") and node.attr in DATETIME_NOW:
                found.append((node.lineno, f"{name}.{node.attr}"))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and isinstance(node.func.value, ast.Name) and node.func.value.id == "time"
              and node.func.attr in NOW_BY_DEFAULT and len(node.args) <= NOW_BY_DEFAULT[node.func.attr]):
            found.append((node.lineno, f"time.{node.func.attr}() of now"))
    return found


def system_uses(source: str) -> list[int]:
    """Lines that name the machine's clock object `SYSTEM` other than as a parameter's default."""
    tree = ast.parse(source)
    defaults = {id(d) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                for d in [*f.args.defaults, *f.args.kw_defaults] if d is not None}
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Name) and n.id == "SYSTEM" and id(n) not in defaults]


def modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_no_part_reads_the_machines_clocks_but_the_clock_modules():
    offences = []
    for path in modules():
        rel = path.relative_to(ROOT).as_posix()
        if rel in CLOCK_MODULES:
            continue
        found = [f"{rel}:{line}: {what}" for line, what in clock_reads(path.read_text())]
        if rel in PENDING:
            assert len(found) <= PENDING[rel], f"{rel}: a read added to one not yet on the clock:\n" + "\n".join(found)
            assert len(found) == PENDING[rel], f"{rel}: {len(found)} reads left; lower PENDING to match"
            continue
        offences += found
    offences.sort()
    assert not offences, ("read the time from the clock handed in (flockcal.clock.Clock: monotonic() for "
                          "durations, deadlines and cadences, wall() for stamps, sleep/wait for waits):\n"
                          + "\n".join(offences))


def test_the_machines_clock_is_only_a_default_for_callers_who_give_none():
    offences = [f"{p.relative_to(ROOT).as_posix()}:{line}" for p in modules()
                if p.relative_to(ROOT).as_posix() not in SYSTEM_NAMED | CLOCK_MODULES
                for line in system_uses(p.read_text())]
    assert not offences, "pass the clock in rather than reaching for flockcal.clock.SYSTEM:\n" + "\n".join(offences)


def test_the_scan_tells_a_default_from_a_use():
    # Tried: the machine's clock as a parameter's default (allowed), slept on in a body (not).
    assert system_uses("def f(clock=SYSTEM):\n    clock.sleep(1)\n") == []
    assert system_uses("def f(*, clock=SYSTEM): ...\ndef g():\n    SYSTEM.sleep(1)\n") == [3]


@pytest.mark.parametrize("source, what", [
    ("import time\nx = time.time()\n", "time.time"),
    ("import time\ndef f(clock=time.monotonic): ...\n", "time.monotonic"),
    ("import time\nstart = time.perf_counter()\n", "time.perf_counter"),
    ("import time\ntime.sleep(0.1)\n", "time.sleep"),
    ("import time\nt = time.monotonic_ns()\n", "time.monotonic_ns"),
    ("from time import monotonic\n", "from time import monotonic"),
    ("from datetime import datetime\nd = datetime.now()\n", "datetime.now"),
    ("import datetime\nd = datetime.datetime.utcnow()\n", "datetime.utcnow"),
    ("from datetime import date\nd = date.today()\n", "date.today"),
    ("import time\ns = time.strftime('%H:%M')\n", "time.strftime() of now"),
    ("import time\ns = time.localtime()\n", "time.localtime() of now"),
])
def test_the_scan_finds_each_way_of_reading_the_clock(source, what):
    # Tried: each form the rule forbids, alone in a module: the scan names it.
    assert [w for _, w in clock_reads(source)] == [what]


def test_the_scan_lets_formatting_a_stamp_and_the_injected_clock_through():
    source = ("import time\n"
              "when = time.strftime('%Y-%m-%d', time.localtime(stamp))\n"
              "now = clock.monotonic()\n"
              "clock.wait(event, 0.5)\n")
    assert clock_reads(source) == []
