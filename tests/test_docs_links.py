"""The documentation holds together as files: README.md is a landing page and docs/ the site's pages.

Every relative link and image in README.md and docs/**/*.md points at a file of the repository, and an
anchor at a heading of that file (named as GitHub names headings, which mkdocs.yml makes the site's anchors
too); every page is linked from somewhere; no page cites a document outside the repository. The site's own
checks (the strict build, README's length and commands, page lengths) are tests/test_docs_site.py's.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted(p for p in (ROOT / "docs").rglob("*.md") if "hooks" not in p.parts)]
# Documents that live beside the repository, not in it: a clone has none of them.
OUTSIDE = ("../shared", "/work/", "fob-protocol.md")

FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.M | re.S)
CODE_SPAN = re.compile(r"`+[^`\n]*`+")
LINK = re.compile(r"!?\[(?:[^\]\n]|\](?!\())*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t#]*$", re.M)


def prose(text: str) -> str:
    """The text a reader sees as prose: fenced blocks and code spans removed (links there are not links)."""
    return CODE_SPAN.sub("", FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: its text (links reduced to their words), lower case, punctuation
    dropped (word characters, spaces and hyphens kept), spaces turned into hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for h in HEADING.findall(FENCE.sub("", path.read_text(encoding="utf-8"))):
        s = slug(h)
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def broken_links(page: Path, root: Path) -> list[str]:
    """Each relative link of `page` whose file is missing, leaves `root`, or whose anchor names no heading."""
    problems = []
    for target in LINK.findall(prose(page.read_text(encoding="utf-8"))):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto: — not files
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if root.resolve() not in (dest, *dest.parents):
            problems.append(f"{target} leaves the repository")
        elif not dest.exists():
            problems.append(f"{target}: no file {dest.relative_to(root.resolve())}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{target}: {dest.name} has no heading with anchor #{anchor}")
    return problems


def linked_pages(page: Path) -> set[Path]:
    found = set()
    for target in LINK.findall(prose(page.read_text(encoding="utf-8"))):
        path = target.partition("#")[0]
        if path.endswith(".md") and not re.match(r"[a-z][a-z0-9+.-]*:", path, re.I):
            found.add((page.parent / path).resolve())
    return found


def fenced_lines(text: str) -> list[str]:
    """Every line inside a fenced code block, stripped: the commands a reader copies."""
    return [line.strip() for m in FENCE.finditer(text) for line in m.group(0).splitlines()[1:-1]]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert not broken_links(page, ROOT), broken_links(page, ROOT)


def test_every_docs_page_is_linked_from_the_readme_or_another_page():
    linked = set().union(*(linked_pages(p) for p in PAGES))
    orphans = [str(p.relative_to(ROOT)) for p in PAGES[1:] if p.resolve() not in linked]
    assert not orphans, f"pages nobody links to: {orphans}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_page_cites_a_document_outside_the_repository(page):
    text = page.read_text(encoding="utf-8")
    cited = [(n, s) for n, line in enumerate(text.splitlines(), 1) for s in OUTSIDE if s in line]
    assert not cited, f"{page.name} cites outside files (line, text): {cited}"


def test_the_checker_reports_a_missing_file_a_wrong_anchor_and_a_link_out_of_the_repository(tmp_path):
    # Tried: a page linking a missing file, a heading that is not there, and a file above the root;
    # the good links (same-page anchor, another page's heading, a URL, a link inside code) pass.
    # Every document's name is made from the temporary folder's: no name here reads as one of the repository's.
    def md(stem: str) -> str:
        return f"{tmp_path.name}-{stem}" + ".md"

    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / md("other")).write_text("# Other\n\n## Measured (bench_x.py, one core)\n")
    page = tmp_path / "docs" / md("page")
    page.write_text(
        "# Page\n\n## WebSocket `/ws/live`\n\n"
        f"[ok]({md('other')}#measured-bench_xpy-one-core) [ok](#websocket-wslive) [url](https://example.org/x)\n"
        f"`[code]({md('nowhere')})`\n\n```\n[fenced]({md('nowhere')})\n```\n"
        f"[gone]({md('missing')}) [bad anchor]({md('other')}#no-such-heading) [out](../../{md('outside')})\n"
    )
    problems = broken_links(page, tmp_path)
    assert len(problems) == 3, problems
    assert any(md("missing") in p for p in problems)
    assert any("#no-such-heading" in p for p in problems)
    assert any("leaves the repository" in p for p in problems)


def tour_lines() -> list[str]:
    text = README.read_text(encoding="utf-8")
    m = re.search(r"^## A tour\n(.*?)(?=^## )", text, re.M | re.S)
    assert m, 'README.md has no "## A tour" section'
    return [ln for ln in fenced_lines(m.group(1)) if ln.startswith("flockcal ")]


# What each tour command needs beyond `pip install .`: the module it imports and the extra that brings it
# (a new user ran the tour after the README's install and met these; issue #29).
NEEDS = {"fit-markers": ("optical", "ezc3d"), "batch": ("batch", "dask")}


def test_each_tour_line_that_needs_an_extra_names_it():
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    base = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    seen = set()
    for line in tour_lines():
        command = line.split()[1]
        if command not in NEEDS:
            continue
        extra, module = NEEDS[command]
        seen.add(command)
        assert any(d.startswith(module) for d in extras[extra]), f"the {extra!r} extra does not bring {module}"
        assert not any(d.startswith(module) for d in base), f"{module} is a plain dependency now: drop the note"
        assert f"pip install '.[{extra}]'" in line, f"the tour line {line!r} does not say it needs '.[{extra}]'"
    assert seen == set(NEEDS), f"the tour lost its {set(NEEDS) - seen} line(s); update NEEDS"


CODE = [p for d in ("flockcal", "server", "solver", "drivers", "simulator") for p in sorted((ROOT / d).rglob("*"))
        if p.suffix in (".py", ".js", ".html") and "vendor" not in p.parts]
CITED = re.compile(r"docs/([\w-]+\.md)#([\w-]+)")
# A README section cited by name ("README.md, "Progress"", "the README's server section"): those moved to docs/.
README_SECTION = re.compile(r"README(?:\.md)?(?:'s \w+ section|,? \\?\"[^\"\\]+\\?\"|,? \(?\"[A-Z])")


def test_what_the_code_tells_users_cites_pages_and_headings_that_exist():
    # Issue #29: the OpenAPI description ("the README's server section") and the HTML report ("README,
    # Progress") pointed at sections that had moved to docs/.
    problems = []
    for path in CODE:
        text = path.read_text(encoding="utf-8")
        for page, anchor in CITED.findall(text):
            if not (ROOT / "docs" / page).exists() or anchor not in anchors(ROOT / "docs" / page):
                problems.append(f"{path.relative_to(ROOT)}: docs/{page}#{anchor}")
        problems += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in README_SECTION.finditer(text)]
    assert CODE and not problems, problems
