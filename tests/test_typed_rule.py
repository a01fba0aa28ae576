"""One typed currency in the service (docs/internals.md, "flockcal.server"): a fit is a `Calibration`, an event
an `events.Event`, a frame batch `Frames`, from where they are made to the route that answers; server/ looks a
value up by a string key only in a protocol's or a file format's own mapping, at the edge.

Statically, over the syntax tree of every module of server/: each string-key lookup (`x["key"]`, `x.get("key")`;
a route decorator such as `@router.get("/stats")` is none) is one this table lists for its file, with why the
mapping is not ours to type, and there are fewer than 60 of them (issue 49's bar). A new lookup of a fit's or an
event's field fails here: read the typed object instead. `python tests/test_typed_rule.py` prints them all.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "server"
BAR = 60

ASGI = {"type", "path", "headers", "text", "code"}  # the ASGI scope and messages (the ASGI specification's keys)
# The keys each file may look up, and why they are a mapping of someone else's.
EDGE = {
    "server/app.py": ASGI | {"content-length"}  # the body limit and docs-page middlewares: ASGI, HTTP headers
    | {"error", "pattern"},  # pydantic's error `ctx`, whose keys depend on the error's type
    "server/auth.py": {"authorization", "origin", "host"},  # HTTP request headers
    "server/downloads.py": ASGI,
    "server/hosts.py": ASGI,
    "server/wsgate.py": ASGI,
    "server/routes/live.py": ASGI | {"token"},  # the websocket's receive messages and its query string
    "server/routes/status.py": {"Link"},  # a response header
    "server/settings.py": {"XDG_DATA_HOME", "baud"},  # the environment; a device URL's query string
    # The frame log file's JSON header line, and its version-1 record (a numpy structured dtype), where the
    # file is parsed: past that, a `framelog.Header` and `Frames`.
    "server/framelog.py": {"format", "names", "version", "rate_hz"},
    "server/frameblocks.py": {"time", "rot", "pos", "valid"},
    # The Pos_Quat message as VRPN sends it (`vrpn.REPORT`, a numpy structured dtype written in place per frame).
    "server/vrpn.py": {"length", "sender", "type", "sensor", "sensor_pad", "sec", "usec", "pos", "quat"},
    # JSON schema written by the fields' json_schema_extra hooks; the bearer scheme in the document's components.
    "server/openapi.py": {"enum", "anyOf", "components", "securitySchemes"},
    "server/sessions.py": {"preset"},  # the preset name the service writes beside a session's skeleton file
}


def string_key_lookups(source: str) -> list[tuple[int, str, str]]:
    """(line, key, code) of each subscript by a string literal and each `.get("literal", …)` call in `source`,
    route decorators left out."""
    tree = ast.parse(source)
    decorators = {id(d) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                  for d in f.decorator_list}
    found = []
    for node in ast.walk(tree):
        key = None
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
            key = node.slice.value
        elif (isinstance(node, ast.Call) and id(node) not in decorators and isinstance(node.func, ast.Attribute)
              and node.func.attr == "get" and node.args and isinstance(node.args[0], ast.Constant)):
            key = node.args[0].value
        if isinstance(key, str):
            found.append((node.lineno, key, ast.unparse(node)[:90]))
    return sorted(found)


def server_lookups(root: Path = ROOT) -> dict[str, list[tuple[int, str, str]]]:
    return {str(p.relative_to(root)): found for p in sorted((root / PACKAGE).rglob("*.py"))
            if (found := string_key_lookups(p.read_text(encoding="utf-8")))}


def test_the_service_looks_up_string_keys_only_at_its_edges():
    lookups = server_lookups()
    stray = [f"{path}:{line}: {code}" for path, found in lookups.items() for line, key, code in found
             if key not in EDGE.get(path, ())]
    assert not stray, ("string-key lookups of data the service owns (read the typed Calibration, Event, Frames "
                       "or Settings instead; a protocol's own mapping goes in EDGE with why):\n" + "\n".join(stray))
    total = sum(map(len, lookups.values()))
    assert 0 < total < BAR, f"server/ looks up {total} string keys (the bar is under {BAR})"


def test_the_rule_sees_subscripts_and_gets_but_not_route_decorators():
    # Tried: a fit's field read three ways, a variable key, an int index and a route decorator.
    source = ('@router.get("/x")\ndef f(fit, i, k):\n    return fit["joints"], fit.get("bones"), '
              'fit.get("slips", []), fit[k], fit[0], router.get("/y")\n')
    assert [(line, key) for line, key, _ in string_key_lookups(source)] == [
        (3, "/y"), (3, "bones"), (3, "joints"), (3, "slips")]


if __name__ == "__main__":
    found = server_lookups()
    for path, rows in found.items():
        for line, _key, code in rows:
            print(f"{path}:{line}: {code}")
    print(sum(map(len, found.values())))
