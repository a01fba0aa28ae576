"""The docs site holds what issue 49 asked of it: a strict build, an API and REST reference made from the
code, a README a new user can follow, pages a user can read.

- `mkdocs build --strict` passes (every page in the nav, every link and anchor resolves; mkdocs.yml), and
  its generated pages list every public object of each package's `__all__` and every REST operation of
  the service's OpenAPI document (docs/hooks/generate.py makes them at build time);
- README.md: at most 70 lines; its "Set up" section holds exactly two commands, the venv set-up and the test
  command, the second being exactly what .ci/run runs; every tour line names commands and options the
  command line takes (tests/test_docs_tour.py runs them);
- each page of docs/ under 350 lines but docs/history.md and the architecture page's module map
  (LONG_PAGES); README and every page but docs/history.md together carry at most 10 dated stamps, a date
  being a YYYY-MM-DD anywhere in the text, code blocks included (the story of a figure is history.md's);
- docs/performance.md lists every script in benchmarks/.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS / "hooks"))
import generate  # noqa: E402  (docs/hooks/generate.py: the build's own generators, read for what they list)

# The bounds, no margin: they are the promise.
MAX_README_LINES = 70
MAX_PAGE_LINES = 350
MAX_DATED_STAMPS = 10
SET_UP = "python3 -m venv .venv && . .venv/bin/activate && pip install . && flockcal serve"
# The history page keeps every round and dated re-measurement out of the other pages: the bounds do not
# apply to it. The architecture page's module map is for maintainers (tests/test_docs_symbols.py holds it to
# the code) and is longer than a user page; it is held to the dated-stamp bound like every other page.
HISTORY = "history.md"
LONG_PAGES = {
    "internals.md": "the architecture page and the module map the maintainers keep (tests/test_docs_symbols.py)",
}
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
FENCE = re.compile(r"^(```|~~~)[^\n]*\n(.*?)^\1[^\n]*$", re.M | re.S)


def pages() -> list[Path]:
    return sorted(p for p in DOCS.rglob("*.md") if "hooks" not in p.relative_to(DOCS).parts)


def user_pages() -> list[Path]:
    """Every page but the history: what the dated-stamp bound counts."""
    return [p for p in pages() if str(p.relative_to(DOCS)) != HISTORY]


def fenced_lines(text: str) -> list[str]:
    return [ln.strip() for m in FENCE.finditer(text) for ln in m.group(2).splitlines() if ln.strip()]


def section(title: str) -> str:
    m = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", README.read_text(encoding="utf-8"), re.M | re.S)
    assert m, f'README.md has no "## {title}" section'
    return m.group(1)


def ci_command() -> str:
    """What .ci/run runs: its last line that is neither a comment nor shell set-up."""
    lines = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()]
    commands = [ln for ln in lines if ln and not ln.startswith(("#", "set ", "cd "))]
    assert commands, ".ci/run holds no command"
    return commands[-1]


# --- the site ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None:
        pytest.skip("mkdocs is not installed: pip install '.[docs]' (the test extra brings it)")
    out = tmp_path_factory.mktemp("site")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)], cwd=ROOT,
                         capture_output=True, text=True, timeout=600,
                         env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    problems = [ln for ln in run.stderr.splitlines() if not ln.startswith("INFO")]
    assert run.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(problems[-40:])
    return out


def test_the_site_builds_strictly_with_every_page(site):
    # Tried: the build itself (the fixture: strict, so a broken link or anchor, a page left out of the nav or
    # a docstring griffe cannot read fails it); here, that each page of docs/ became a page of the site.
    for page in pages():
        rel = page.relative_to(DOCS).with_suffix("")
        built = site / ("index.html" if rel.name == "index" else rel / "index.html")
        assert built.exists(), f"docs/{page.relative_to(DOCS)} was not built ({built.relative_to(site)})"


def test_the_api_reference_lists_every_public_object(site):
    # Tried: every name of each package's __all__ against the built page of its package: documented there
    # under the name a user imports, or (a name flockcal's top level exports too) linked to that entry.
    top = set(generate.public_names("flockcal"))
    for page in sorted((DOCS / "api").glob("*.md")):
        m = re.search(r"<!-- generated: api ([\w.]+) -->", page.read_text(encoding="utf-8"))
        assert m, f"docs/api/{page.name} names no package"
        package = m.group(1)
        html = (site / "api" / page.stem / "index.html").read_text(encoding="utf-8")
        for name, module in generate.public_names(package):
            anchor = f"{module}.{name}"
            if package != "flockcal" and (name, module) in top:
                assert f'#{anchor}"' in html, f"{package}.{name}: no link to flockcal.{name} on api/{page.stem}"
            else:
                assert f'id="{anchor}"' in html and f"{package}.{name}" in html, \
                    f"{package}.{name} is not documented on api/{page.stem}"
    packages = {re.search(r"api ([\w.]+)", p.read_text()).group(1) for p in (DOCS / "api").glob("*.md")}
    expected = {"flockcal", *(f"flockcal.{p}" for p in ("solver", "drivers", "simulator", "server", "exports"))}
    assert packages == expected, f"API pages for {packages}, not {expected}"


def test_the_rest_reference_lists_every_operation_of_the_openapi_document(site):
    # Tried: each (method, path) of the document the service builds, against the built REST page.
    html = (site / "rest" / "index.html").read_text(encoding="utf-8")
    doc = generate.openapi_document()
    missing = [f"{m.upper()} {p}" for p, ops in doc["paths"].items() for m in ops
               if f"{m.upper()} <code>{p}</code>" not in html]
    assert doc["paths"] and not missing, f"REST operations not on the page: {missing}"
    for schema in doc["components"]["schemas"]:
        assert f'id="{schema.lower()}"' in html, f"schema {schema} not on the REST page"


# --- README ------------------------------------------------------------------------------------------
def test_readme_is_at_most_70_lines():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}): move detail into docs/"


def test_readme_set_up_is_the_venv_command_and_the_ci_command():
    # Tried: the Set up section's commands, exactly two: the simulator's set-up in a venv, and .ci/run's.
    commands = fenced_lines(section("Set up"))
    assert commands == [SET_UP, ci_command()], (
        f"README's Set up must hold exactly {SET_UP!r} and .ci/run's command {ci_command()!r}; it holds {commands}")


def test_the_test_command_builds_the_site_strictly_in_a_venv():
    command = ci_command()
    assert "python3 -m venv .venv && . .venv/bin/activate" in command
    assert "mkdocs build --strict" in command
    for package in ("chromium", "assimp-utils", "faketime", "nodejs", "npm", "python3-venv"):
        assert re.search(rf"apt-get install[^;)]*\b{package}\b", command), f"the apt line lacks {package}"


def tour() -> list[list[str]]:
    """Each tour line's words up to a pipe or a redirection (the shell's, not the command's)."""
    lines = [ln for ln in fenced_lines(section("A tour")) if ln.startswith("flockcal ")]
    out = []
    for ln in lines:
        words = shlex.split(ln, comments=True)
        cut = next((i for i, w in enumerate(words) if w in ("|", ">", ">>", "&&", ";", "&")), len(words))
        out.append(words[:cut])
    return out


def test_each_tour_line_is_a_command_line_flockcal_takes():
    # Tried: every tour line through the command line's own parser (nothing run): a renamed command or
    # option fails here before a new user meets it.
    from flockcal.cli import build_parser

    lines = tour()
    assert len(lines) >= 8, lines
    for words in lines:
        try:
            args = build_parser(words[1]).parse_args(words[1:])
        except SystemExit as exc:
            pytest.fail(f"{' '.join(words)}: the command line refuses it (exit {exc.code})")
        assert getattr(args, "func", None), words


# --- the pages ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("page", [p for p in user_pages() if str(p.relative_to(DOCS)) not in LONG_PAGES],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_each_user_page_is_under_350_lines(page):
    n = len(page.read_text(encoding="utf-8").splitlines())
    assert n < MAX_PAGE_LINES, f"{page.relative_to(ROOT)} has {n} lines: split it, or move history to docs/history.md"


def test_readme_and_the_user_pages_carry_at_most_10_dated_stamps():
    found = [(p.relative_to(ROOT), d) for p in [README, *user_pages()]
             for d in DATE.findall(p.read_text(encoding="utf-8"))]
    assert len(found) <= MAX_DATED_STAMPS, f"{len(found)} dated stamps (at most {MAX_DATED_STAMPS}): {found}"


def test_the_exempt_pages_exist():
    for name in [HISTORY, *LONG_PAGES]:
        assert (DOCS / name).exists(), f"docs/{name} is gone: update HISTORY or LONG_PAGES"


def test_performance_lists_every_benchmark():
    # Tried: every script in benchmarks/ against docs/performance.md's text.
    text = (DOCS / "performance.md").read_text(encoding="utf-8")
    missing = [p.name for p in sorted((ROOT / "benchmarks").glob("*.py")) if f"benchmarks/{p.name}" not in text]
    assert not missing, f"docs/performance.md does not list {missing}"


def test_the_checks_count_what_they_should(tmp_path):
    # Tried: the date and command readers on text made here.
    text = "a 2026-12-05 figure\n```sh\nflockcal fit take.npz   # a comment\n```\n"
    assert DATE.findall(text) == ["2026-12-05"]
    assert fenced_lines(text) == ["flockcal fit take.npz   # a comment"]
    assert shlex.split("flockcal fit take.npz   # a comment", comments=True) == ["flockcal", "fit", "take.npz"]
