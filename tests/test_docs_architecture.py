"""docs/internals.md's diagram of the frame's path and the threads, and docs/server.md's thread table, are
what the code runs (issue 49: the architecture page cannot drift).

Read from the code (its syntax trees, nothing imported): every thread the service's packages start, by the
OS name it gives itself (`flockcal.threads.name_os_thread`) or the `fc-` name it is started under; an
`f"fc-pump-{i}"` counts as `fc-pump-N`. Held: the diagram names exactly those threads; every thread is named
(a thread started with neither would be missing from both); every module path the diagram gives exists and
defines the names it says it does; the REST routes run where the diagram says (plain functions on AnyIO's
worker threads, an `async def` route on the event loop, named there); server.md's table lists the same
threads as the diagram.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
INTERNALS = ROOT / "docs" / "internals.md"
SERVER_PAGE = ROOT / "docs" / "server.md"
# The service's packages; the simulator's own fake-tracker thread serves `flockcal simulate --pty`, not the service.
SERVICE_CODE = ("flockcal", "drivers", "server", "solver")
MARKER = "<!-- architecture diagram: tests/test_docs_architecture.py -->"
THREAD = re.compile(r"\bfc-[a-z]+(?:-[a-z]+)*(?:-N)?\b")
ROUTE = re.compile(r"^(get|post|put|delete|patch)$")


def diagram() -> str:
    text = INTERNALS.read_text(encoding="utf-8")
    assert MARKER in text, f"docs/internals.md lost its diagram's marker {MARKER!r}"
    m = re.search(r"```[^\n]*\n(.*?)\n```", text[text.index(MARKER):], re.S)
    assert m, "no fenced diagram after the marker"
    return m.group(1)


def _name_of(node: ast.expr) -> str | None:
    """A thread name given as a literal, or as an f-string whose fields stand for a number (`N`)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "N" for v in node.values)
    return None


def _callee(call: ast.Call) -> str:
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def code_threads() -> tuple[set[str], list[str]]:
    """(the service's thread names, problems: threads started with no name the docs could give)."""
    names, problems = set(), []
    for folder in SERVICE_CODE:
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            named_by = {}  # function name -> the OS name it gives the thread running it
            for fn in ast.walk(tree):
                if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    for call in (n for n in ast.walk(fn) if isinstance(n, ast.Call)):
                        if _callee(call) == "name_os_thread" and call.args and _name_of(call.args[0]):
                            named_by[fn.name] = _name_of(call.args[0])
            names |= set(named_by.values()) - {None}
            for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call) and _callee(n) == "Thread"):
                kw = {k.arg: k.value for k in call.keywords}
                given = _name_of(kw["name"]) if "name" in kw else None
                target = kw.get("target")
                target = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)
                if given and given.startswith("fc-"):
                    names.add(given)
                elif target not in named_by:
                    problems.append(f"{path.relative_to(ROOT)}:{call.lineno}: a thread named {given!r} whose "
                                    f"target {target!r} gives itself no fc- name")
    return names, problems


def test_every_thread_the_service_starts_has_an_fc_name():
    names, problems = code_threads()
    assert names, "found no thread in the code: the reader changed?"
    assert not problems, "\n".join(problems)


def test_the_diagram_names_exactly_the_threads_the_code_starts():
    names, _ = code_threads()
    drawn = set(THREAD.findall(diagram()))
    assert drawn == names, f"in the code, not the diagram: {names - drawn}; in the diagram, not the code: {drawn - names}"


def _defined(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}


def test_the_diagrams_modules_exist_and_define_what_it_names():
    text = diagram()
    problems = []
    for rel in set(re.findall(r"\b((?:[\w]+/)+[\w]+\.py|(?:[\w]+/)+)(?=\))", text)):
        if not (ROOT / rel).exists():
            problems.append(f"no {rel} in the repository")
    for name, rel in re.findall(r"\b([A-Za-z_]\w*) \(((?:[\w]+/)+[\w]+\.py)\)", text):
        if (ROOT / rel).exists() and name not in _defined(ROOT / rel):
            problems.append(f"{rel} defines no {name}")
    classes = set().union(*(_defined(p) for d in (*SERVICE_CODE, "simulator") for p in (ROOT / d).rglob("*.py")))
    for name in re.findall(r"\b[A-Z][a-z]+(?:[A-Z][a-z]+)+\b", text):
        if name not in classes:
            problems.append(f"no class {name} in the code")
    for cls, attr in re.findall(r"\b([A-Z]\w+)\.([a-z_]\w*)", text):
        owners = [p for d in SERVICE_CODE for p in (ROOT / d).rglob("*.py") if f"class {cls}" in p.read_text()]
        if not any(re.search(rf"def {attr}\b", p.read_text()) for p in owners):
            problems.append(f"no {cls}.{attr}")
    assert not problems, "\n".join(problems)


def routes() -> tuple[list[str], list[str]]:
    """(plain-function routes, async routes) of server/routes/, websockets left out."""
    sync, asyn = [], []
    for path in sorted((ROOT / "server" / "routes").glob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            verbs = [d.func.attr for d in fn.decorator_list
                     if isinstance(d, ast.Call) and isinstance(d.func, ast.Attribute) and ROUTE.match(d.func.attr)]
            if verbs:
                (asyn if isinstance(fn, ast.AsyncFunctionDef) else sync).append(fn.name)
    return sync, asyn


def test_the_rest_routes_run_where_the_diagram_says():
    # Tried: every route function of server/routes. FastAPI runs a plain `def` route on AnyIO's worker
    # threads and an `async def` one on the event loop itself.
    sync, asyn = routes()
    text = diagram()
    assert sync and "worker threads (AnyIO)" in text, "REST routes are plain functions: the diagram must say worker threads"
    missing = [name for name in asyn if name not in text]
    assert not missing, f"async routes run on the event loop; the diagram does not name {missing}"


def test_server_md_lists_the_same_threads():
    rows = re.findall(r"^\| (.+?) \|", SERVER_PAGE.read_text(encoding="utf-8"), re.M)
    listed = {t for row in rows for t in THREAD.findall(row)}
    names, _ = code_threads()
    assert listed == names, f"server.md's thread table: missing {names - listed}, extra {listed - names}"
    assert any("worker threads" in row for row in rows), "server.md's table must say where the REST routes run"


def test_the_readers_find_what_they_should(tmp_path):
    # Tried: the thread reader on code made here: a named thread, one that names itself, an f-string name,
    # and one with no name at all (reported).
    src = tmp_path / "flockcal" / "x.py"
    src.parent.mkdir()
    src.write_text(
        "import threading\nfrom flockcal.threads import name_os_thread\n"
        "class A:\n    def go(self):\n        threading.Thread(target=self._run, name='py-a').start()\n"
        "        threading.Thread(target=self._tick, name='fc-tick').start()\n"
        "        threading.Thread(target=self._bare).start()\n"
        "    def _run(self, i=1):\n        name_os_thread(f'fc-run-{i}')\n    def _bare(self):\n        pass\n"
    )
    import test_docs_architecture as mod

    saved = mod.ROOT, mod.SERVICE_CODE
    try:
        mod.ROOT, mod.SERVICE_CODE = tmp_path, ("flockcal",)
        names, problems = mod.code_threads()
    finally:
        mod.ROOT, mod.SERVICE_CODE = saved
    assert names == {"fc-run-N", "fc-tick"}
    assert len(problems) == 1 and "_bare" in problems[0]
