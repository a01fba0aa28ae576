"""Every module, class, function and file that README.md and docs/**/*.md name in code exists (issue 33).

What counts as a reference (docs/development.md states the same convention for writers):

- In a code span (`…`) outside fenced blocks, its head — the dotted name it starts with:
  * a dotted name whose first part is a module of the repository (`flockcal.solver.fits`,
    `fits.pair_fits`, `server.fitting.fit_calibration`: any tail of a module's dotted name), a class of it
    (`PairFits.rms`), a variable name the pages use for a known type (`take.names`: VARIABLES below) or an
    installed package (`serial.serial_for_url`): each part must exist, read in turn as a module, a name
    that module defines, then an attribute of that class (method, property, field, what its methods set
    on `self`). A part past a class's attribute is not followed (its type is not known here).
  * a name directly followed by `(` (`solve(...)`, `make_take(path)`): a function or class defined in
    the repository (Python, or the pages' scripts in server/static); keywords the span gives
    (`detect_slips(take, batch_s=10.0)`) must be parameters of the function it resolves to, and a
    number, string, True/False/None given for one must be its default (pages write signatures, not
    example calls, in code spans; an example is a fenced block).
  * a capitalised name alone (`SlipWatch`, `Take`): a class (or other such name) defined in the
    repository, tests and benchmarks included; NOT_OURS lists the few that belong to other programs.
  * a path of the repository (`tests/server_helpers.py`, `routes/status.py`): a file or folder of that
    name from the repository root, the page's folder or a package folder, when its first folder is one
    of those (`DIR/summary.csv` is a user's file) and git does not ignore it; globs and placeholders
    (`benchmarks/*.py`, `tests/test_x.py`) are not paths. A bare source file name (`fitting.py`) must be
    a file somewhere in the repository; other file names (`take.npz`) are a user's.
- Not references: spans starting with a dot (`.names`, an attribute of what the sentence is about),
  single lowercase words (options, JSON fields, variables), dotted names whose head is nothing above
  (`args.func`), commands (`flockcal fit`), URLs, environment variables.
- In fenced python blocks: every import resolves, and a name bound by an import, or by a call of a class or
  of a function whose return annotation is a repository class (`skeleton = load_skeleton(...)`), has the
  attributes the block uses on it, and the keywords the block passes.
"""

from __future__ import annotations

import ast
import builtins
import importlib
import importlib.util
import inspect
import re
import subprocess
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import pytest

from layers import LAYERS, PACKAGE_DIRS, ROOT, import_edges, module_files

PAGES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if "hooks" not in p.parts)]

FENCE = re.compile(r"^(```|~~~)(\w*).*?\n(.*?)^\1[^\n]*$", re.M | re.S)
SPAN = re.compile(r"(?<!`)`((?:[^`\n]|\n(?!\s*\n))+)`(?!`)")  # a span may wrap, never across a blank line
HEAD = re.compile(r"[A-Za-z_][\w.]*")
PATH = re.compile(r"^\.?[\w.-]+(?:/[\w.-]+)*/?$")
# The names the pages give to things of a known type, in prose code spans (`take.names`, `cal.parent_map()`).
VARIABLES = {
    "take": "flockcal.takes.Take",
    "cal": "flockcal.solver.calibration.Calibration",
    "calibration": "flockcal.solver.calibration.Calibration",
    "acc": "flockcal.solver.accumulator.GramAccumulator",
    "skeleton": "flockcal.solver.known_skeleton.Skeleton",
    "reader": "flockcal.drivers.reader.TrackerReader",
    "watch": "flockcal.solver.slippage.watch.SlipWatch",
    "settings": "flockcal.server.settings.Settings",
    "service": "flockcal.server.service.Service",
}
ALIASES = {"np": "numpy"}
# CamelCase words in code spans that are not this repository's: another program's settings or classes.
NOT_OURS = {
    "ExecStart": "systemd unit setting (docs/kiosk.md)",
    "RestartPreventExitStatus": "systemd unit setting",
    "LimitNOFILE": "systemd unit setting",
    "FlockStandalone": "VR Juggler's driver class, cited as a source (docs/protocol.md)",
    "Host": "the HTTP header",
}
# A dotted word ending in one of these is a file name (`take.npz`, `ID.fobraw.part`), not code.
FILE_SUFFIXES = {"npz", "fobraw", "part", "json", "csv", "bvh", "glb", "gltf", "html", "c3d", "py", "js", "md",
                 "css", "toml", "txt", "sqlite3", "frames", "service", "png", "svg", "yml"}


# --- the code's names -------------------------------------------------------------------------------
@dataclass
class ClassInfo:
    attrs: set[str] = field(default_factory=set)  # methods, class-level names, what methods set on self


@cache
def code_index():
    """(modules {dotted: file}, classes {name: [ClassInfo]}, defined names {every def/class name})."""
    modules = module_files()
    classes: dict[str, list[ClassInfo]] = {}
    defined: set[str] = set()
    for path in modules.values():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                defined.add(node.name)
            elif isinstance(node, ast.ClassDef):
                defined.add(node.name)
                info = ClassInfo()
                for stmt in node.body:  # the class body's own names (a method's locals are not attributes)
                    if isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                        info.attrs.add(stmt.name)
                    elif isinstance(stmt, (ast.Assign, ast.AnnAssign)):
                        for t in stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]:
                            info.attrs |= {n.id for n in ast.walk(t) if isinstance(n, ast.Name)}
                info.attrs |= {n.attr for n in ast.walk(node)  # what its methods set on self
                               if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
                               and isinstance(n.value, ast.Name) and n.value.id == "self"}
                classes.setdefault(node.name, []).append(info)
    for path in [*sorted((ROOT / "tests").glob("*.py")), *sorted((ROOT / "benchmarks").glob("*.py"))]:
        # Helpers the pages name (`ServerThread` of tests/server_helpers.py): names only, never imported.
        defined |= {n.name for n in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
                    if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}
    for path in sorted((ROOT / "server" / "static").glob("*.js")):
        text = path.read_text(encoding="utf-8")
        defined |= set(re.findall(r"\b(?:function\*?|class)\s+([A-Za-z_$][\w$]*)", text))
        defined |= set(re.findall(r"^\s+(?:async\s+|static\s+|get\s+|set\s+)?([A-Za-z_$][\w$]*)\s*\([^)]*\)\s*\{", text, re.M))
        defined |= set(re.findall(r"\b(?:const|let)\s+([A-Za-z_$][\w$]*)\s*=", text))
    return modules, classes, defined


def _import(name: str):
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def _attr_of_class(cls, attr: str) -> bool:
    """`attr` exists on class `cls` or its instances: dynamically (inherited, properties, dataclass fields)
    or set on self by a method of it or of a repository base class."""
    if hasattr(cls, attr) or attr in getattr(cls, "__dataclass_fields__", {}):
        return True
    _, classes, _ = code_index()
    return any(attr in info.attrs for klass in inspect.getmro(cls) for info in classes.get(klass.__name__, [])
               if klass.__module__.startswith("flockcal"))


_INSTANCE = object()  # what `_walk` gives past a class's attribute: something, of a type not followed


def _walk(obj, parts: list[str]) -> tuple[object, str | None]:
    """Follow `parts` from `obj` (a module or class); (what it resolved to, the first part that did not)."""
    for part in parts:
        if inspect.ismodule(obj):
            if hasattr(obj, part):
                obj = getattr(obj, part)
                continue
            sub = _import(f"{obj.__name__}.{part}")
            if sub is None:
                return None, part
            obj = sub
        elif inspect.isclass(obj):
            if not _attr_of_class(obj, part):
                return None, part
            return _INSTANCE, None  # an attribute's own type is not followed
        else:
            return _INSTANCE, None
    return obj, None


def heads(first: str) -> list[object]:
    """What a reference's first part can stand for: modules (by any tail of their name), classes, a
    variable's type, an installed package."""
    modules, classes, _ = code_index()
    out = []
    for name in modules:
        if name == first or name.endswith("." + first):
            mod = _import(name)
            if mod is not None:
                out.append(mod)
    if first in classes:
        for name in modules:
            mod = _import(name)
            cls = getattr(mod, first, None)
            if inspect.isclass(cls) and cls.__module__ == name:
                out.append(cls)
                break
    if first in VARIABLES:
        mod, _, cls = VARIABLES[first].rpartition(".")
        out.append(getattr(importlib.import_module(mod), cls))
    return out


def resolve(dotted: str) -> tuple[bool, list[object], str]:
    """(is a reference, what it resolves to (empty if nothing), why not) for a dotted name."""
    parts = dotted.split(".")
    if dotted.startswith("flockcal."):
        for k in range(len(parts), 0, -1):
            mod = _import(".".join(parts[:k]))
            if mod is not None:
                obj, bad = _walk(mod, parts[k:])
                return True, ([] if bad else [obj]), f"{'.'.join(parts[:k])} has no {bad!r}"
        return True, [], "no such module"
    # The longest leading run of parts that names a module tail wins (`server.fitting.x` before `server`).
    for k in range(len(parts), 0, -1):
        found = heads(".".join(parts[:k])) if k > 1 else heads(parts[0])
        if found:
            hits = []
            for obj in found:
                got, _ = _walk(obj, parts[k:])
                if got is not None:
                    hits.append(got)
            return True, hits, f"no {'.'.join(parts[k:])!r} in {', '.join(_label(f) for f in found)}"
    external = ALIASES.get(parts[0], parts[0])
    if external not in ("self", "cls") and importlib.util.find_spec(external) is not None:
        obj, bad = _walk(importlib.import_module(external), parts[1:])
        return True, ([] if bad else [obj]), f"{external} has no {bad!r}"
    return False, [], ""


def _label(obj) -> str:
    return getattr(obj, "__name__", repr(obj)) if inspect.ismodule(obj) else f"class {obj.__qualname__}"


# --- keywords in a signature span ---------------------------------------------------------------------
def _top_level_keywords(args: str) -> dict[str, str]:
    """{keyword: value text} of `name=value` items at the top level of a call's argument text."""
    items, depth, cur = [], 0, ""
    for ch in args:
        if ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += ch
    items.append(cur)
    out = {}
    for item in items:
        m = re.fullmatch(r"\s*([A-Za-z_]\w*)\s*=\s*(.*?)\s*", item, re.S)
        if m and not m.group(2).startswith("="):
            out[m.group(1)] = m.group(2)
    return out


def _call_args(text: str, start: int) -> str | None:
    """The text between the `(` at `start` and its closing bracket, or None when the span cuts it off."""
    depth = 0
    for k in range(start, len(text)):
        depth += text[k] in "([{"
        depth -= text[k] in ")]}"
        if depth == 0:
            return text[start + 1:k]
    return None


def keyword_problems(obj, args: str) -> list[str]:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return []
    params = sig.parameters
    problems = []
    for kw, value in _top_level_keywords(args).items():
        if kw not in params or params[kw].kind in (inspect.Parameter.VAR_KEYWORD, inspect.Parameter.VAR_POSITIONAL):
            problems.append(f"no parameter {kw!r}")
            continue
        try:
            given = ast.literal_eval(value)
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            continue
        default = params[kw].default
        if (isinstance(given, (int, float, str, bool, type(None))) and default is not inspect.Parameter.empty
                and isinstance(default, (int, float, str, bool, type(None))) and given != default):
            problems.append(f"{kw}={value}, but its default is {default!r}")
    return problems


# --- the pages' references ----------------------------------------------------------------------------
def prose_and_blocks(text: str) -> tuple[str, list[tuple[str, str, int]]]:
    """The page with fenced blocks blanked (line numbers kept), and its blocks (language, body, first line)."""
    blocks = []

    def blank(m):
        blocks.append((m.group(2), m.group(3), text[:m.start(3)].count("\n") + 1))
        return "\n" * m.group(0).count("\n")

    return FENCE.sub(blank, text), blocks


def path_bases(page: Path) -> list[Path]:
    return [ROOT, page.parent, *(ROOT / d for d in PACKAGE_DIRS.values())]


def is_path(span: str, page: Path) -> bool:
    """A path of the repository: its first folder is one of the repository's (from the root, the page's
    folder or a package folder), it is no glob or placeholder, and git does not ignore it (`artifacts/`,
    npm's `tests/gltf/node_modules`: made by running things, not kept)."""
    if "/" not in span or PATH.match(span) is None or "*" in span or "_x." in span:
        return False
    first = span.split("/")[0]
    if not any((base / first).is_dir() for base in path_bases(page)):
        return False  # `DIR/summary.csv`, `results/combined.json`: a user's files
    try:
        ignored = any(subprocess.run(["git", "check-ignore", "-q", p], cwd=ROOT).returncode == 0
                      for p in (span.rstrip("/"), span.rstrip("/") + "/"))
    except FileNotFoundError:  # no git: judge by the file alone
        ignored = False
    return not ignored


def path_exists(span: str, page: Path) -> bool:
    return any((base / span.rstrip("/")).exists() for base in path_bases(page))


def span_problems(span: str, page: Path) -> list[str]:
    s = span.strip()
    if s.startswith(".") and not s.startswith("./"):
        return []
    if is_path(s, page):
        return [] if path_exists(s, page) else ["no such file in the repository"]
    m = HEAD.match(s)
    if not m:
        return []
    head = m.group(0).rstrip(".")
    rest = s[len(head):]
    _, _, defined = code_index()
    if "." in head and head.split(".")[-1] in FILE_SUFFIXES:
        if "/" in rest or not re.fullmatch(r"[\w-]+\.(py|js|html|css|md)", head):
            return []  # a file a user makes or names (`take.npz`)
        found = any(True for _ in ROOT.glob(f"**/{head}") if ".git" not in _.parts)
        return [] if found else [f"no file {head} in the repository"]
    if "." in head:
        is_ref, found, why = resolve(head)
        if not is_ref:
            return []
        if not found:
            return [why]
        if rest.startswith("(") and (args := _call_args(s, len(head))) is not None:
            callables = [f for f in found if callable(f) and f is not _INSTANCE]
            if callables and all(keyword_problems(f, args) for f in callables):
                return keyword_problems(callables[0], args)
        return []
    if rest.startswith("("):
        if head not in defined and not hasattr(builtins, head):
            return [f"no function or class {head!r} in the repository"]
        args = _call_args(s, len(head))
        if args is None:
            return []
        found = [f for f in _functions_named(head)]
        if found and all(keyword_problems(f, args) for f in found):
            return keyword_problems(found[0], args)
        return []
    if (rest == "" and re.fullmatch(r"_?[A-Z][a-z0-9]+(?:[A-Z][a-z0-9]*)*", head) and head not in NOT_OURS
            and not hasattr(builtins, head)):
        return [] if head in defined else [f"no class {head!r} in the repository"]
    return []


@cache
def _functions_named(name: str) -> tuple:
    """Every module-level function or class of the repository called `name`, and every method of that name."""
    modules, _, _ = code_index()
    out = []
    for mod_name in modules:
        mod = _import(mod_name)
        if mod is None:
            continue
        obj = getattr(mod, name, None)
        if obj is not None and getattr(obj, "__module__", None) == mod_name and callable(obj):
            out.append(obj)
        for _, cls in inspect.getmembers(mod, inspect.isclass):
            if cls.__module__ == mod_name and name in vars(cls) and callable(vars(cls)[name]):
                out.append(getattr(cls, name))
    return tuple(out)


def block_problems(body: str) -> list[str]:
    """Imports, attributes and keywords of a ```python block (see the module docstring)."""
    try:
        tree = ast.parse(body)
    except SyntaxError:
        lines = [ln for ln in body.splitlines() if re.match(r"\s*(from\s+\S+\s+)?import\s", ln)]
        tree = ast.parse("\n".join(ln.strip() for ln in lines))
    env: dict[str, object] = {}
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            mod = _import(node.module)
            if mod is None:
                problems.append(f"import of {node.module}: no such module")
                continue
            for alias in node.names:
                obj, bad = _walk(mod, [alias.name])
                if bad:
                    problems.append(f"{node.module} has no {alias.name!r}")
                else:
                    env[alias.asname or alias.name] = obj
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if _import(alias.name) is None:
                    problems.append(f"import {alias.name}: no such module")
    for node in ast.walk(tree):  # names bound to the result of a call whose class is known
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and isinstance(node.value, ast.Call) and isinstance(node.value.func, ast.Name)
                and node.value.func.id in env):
            made = _result_class(env[node.value.func.id])
            if made is not None:
                env[node.targets[0].id] = made
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in env:
            owner = env[node.value.id]
            if (inspect.isclass(owner) and not _attr_of_class(owner, node.attr)) or (
                    inspect.ismodule(owner) and _walk(owner, [node.attr])[1]):
                problems.append(f"{node.value.id}.{node.attr}: {_label(owner)} has no {node.attr!r}")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and callable(env.get(node.func.id)):
            try:
                params = inspect.signature(env[node.func.id]).parameters
            except (TypeError, ValueError):
                continue
            takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
            problems += [f"{node.func.id}(…, {k.arg}=…): no such parameter" for k in node.keywords
                         if k.arg and k.arg not in params and not takes_any]
    return problems


def _result_class(obj):
    """The class an instance made by calling `obj` has: `obj` itself, or a function's return annotation."""
    if inspect.isclass(obj):
        return obj
    ann = inspect.signature(obj).return_annotation if callable(obj) else inspect.Signature.empty
    if isinstance(ann, str):
        ann = getattr(inspect.getmodule(obj), ann, None) or _import_class(ann)
    return ann if inspect.isclass(ann) else None


def _import_class(name: str):
    found = heads(name) if name.isidentifier() else []
    return next((f for f in found if inspect.isclass(f)), None)


def page_problems(page: Path) -> list[str]:
    text = page.read_text(encoding="utf-8")
    prose, blocks = prose_and_blocks(text)
    problems = []
    for m in SPAN.finditer(prose):
        span, n = " ".join(m.group(1).split()), prose[:m.start()].count("\n") + 1
        problems += [f"{page.name}:{n}: `{span}`: {p}" for p in span_problems(span, page)]
    for lang, body, first in blocks:
        if lang == "python":
            problems += [f"{page.name}:{first}: python block: {p}" for p in block_problems(body)]
    return problems


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_name_and_path_a_page_gives_in_code_exists(page):
    problems = page_problems(page)
    assert not problems, "\n".join(problems)


def test_the_checker_reports_each_kind_of_reference_that_is_gone(tmp_path):
    # Tried: each form of reference naming something that does not exist (the drift issue 33 found, among
    # them), beside the same form naming something that does; and spans that are no references.
    page = tmp_path / f"{tmp_path.name}.page"  # a temporary name, none of the repository's documents
    page.write_text(
        "`flockcal.solver.fits.pair_fits` `flockcal.solver.fits.no_such` `fits.PairFits.rms` "
        "`PairFits.noise_floor` `sources.TrackerSource` `sources.frames_to_pipeline(feed)` "
        "`solve(acc, names, skeleton=None)` `solve(acc, names, batch_s=None)` "
        "`detect_slips(take, batch_s=10.0)` `detect_slips(take, batch_s=0.25)` `SlipWatch` `SlipWatcher` "
        "`tests/server_helpers.py` `tests/no_such_helper.py` `take.names` `take.no_such` "
        "`serial.serial_for_url` `serial.no_such` `fitting.py` `no_such_module.py`\n\n"
        "Not references: `.anything` `args.func` `DIR/summary.csv` `ExecStart` `flockcal fit` `take.npz`\n\n"
        "```python\nfrom flockcal.exports.skeleton import load_skeleton\nfrom flockcal.nowhere import x\n"
        "skeleton = load_skeleton('a.json')\nskeleton.names\nskeleton.fit(acc)\n```\n",
        encoding="utf-8",
    )
    problems = page_problems(page)
    gone = ["flockcal.solver.fits.no_such", "PairFits.noise_floor", "frames_to_pipeline", "batch_s=None",
            "batch_s=0.25", "SlipWatcher", "no_such_helper.py", "take.no_such", "serial.no_such",
            "no_such_module.py", "flockcal.nowhere", "skeleton.fit"]
    for name in gone:
        assert any(name in p for p in problems), (name, problems)
    assert len(problems) == len(gone), problems


# --- docs/internals.md's table of layers --------------------------------------------------------------
def test_the_table_of_layers_in_internals_is_what_the_modules_import():
    # Tried against the code as it is: each layer's imports of other layers, besides the base layer (every
    # import statement, in functions and under TYPE_CHECKING too: tests/layers.py).
    found = {layer: set() for layer in LAYERS}
    for own, other in import_edges():
        if other != "base":
            found[own].add(other)
    text = (ROOT / "docs" / "internals.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| (\w+) \| [^|]+ \| ([^|]+) \|$", text, re.M)
    table = {layer: {w for w in re.findall(r"\w+", cell) if w in LAYERS} for layer, cell in rows if layer in LAYERS}
    assert set(table) == set(LAYERS), f"internals.md's table of layers lacks {set(LAYERS) - set(table)}"
    assert table == found, {k: (table[k], found[k]) for k in LAYERS if table[k] != found[k]}
