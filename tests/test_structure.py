"""The repository's structure rule on size: no Python file (code, tests, benchmarks) over 600 lines, so a
module stays one thing a maintainer can read whole. Build output, node_modules and hidden folders (.git, a
.venv) are not ours. The other structure rules: tests/test_base_layer.py (no layer cycle), test_docs_links.py.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 600
NOT_OURS = {"build", "node_modules", "dist"}


def python_files(root: Path = ROOT) -> list[Path]:
    """Every .py file under `root` but in hidden folders, build output and node_modules."""
    out = []
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if d not in NOT_OURS and not d.startswith(".")]  # (not walked at all)
        out += [Path(folder) / f for f in files if f.endswith(".py")]
    return sorted(out)


def line_count(path: Path) -> int:
    with path.open("rb") as fh:
        return sum(1 for _ in fh)


def test_no_python_file_is_over_600_lines():
    files = python_files()
    assert len(files) > 100, f"found only {len(files)} Python files under {ROOT}: the walk is wrong"
    over = {str(p.relative_to(ROOT)): n for p in files if (n := line_count(p)) > MAX_LINES}
    assert not over, (f"modules over {MAX_LINES} lines (split each along a seam into modules named for what "
                      f"they hold): {over}")


def test_the_size_rule_sees_a_long_file_and_skips_build_output(tmp_path):
    # Tried: a 601-line module, a 600-line one, and a long file under build/ and node_modules/.
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "long.py").write_text("x = 1\n" * 601)
    (tmp_path / "pkg" / "edge.py").write_text("x = 1\n" * 600)
    for skipped in ("build", "node_modules"):
        (tmp_path / skipped).mkdir()
        (tmp_path / skipped / "gen.py").write_text("x = 1\n" * 900)
    files = python_files(tmp_path)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in files) == ["pkg/edge.py", "pkg/long.py"]
    assert [p.name for p in files if line_count(p) > MAX_LINES] == ["long.py"]
