"""The A/B runner of benchmarks/bench_server.py measures the code it names: each side's service imports the
server and solver of that side's folder. Until 2026-12-05 it started both services from the repository's
root, where `python -m` imported this tree's code on both sides (every A/B ratio was an A/A one)."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(),
                                reason="the A/B runner exports a git revision: needs git and a checkout")


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_server_under_test", ROOT / "benchmarks" / "bench_server.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def imported_from(site: str, cwd: Path) -> set[Path]:
    """Where a child started from `cwd` with `site` first on PYTHONPATH finds the service's and solver's code."""
    probe = "import flockcal.server as a, flockcal.solver as b; print(a.__file__); print(b.__file__)"
    env = {"PYTHONPATH": site, "PATH": "/usr/bin:/bin", "HOME": str(cwd)}
    out = subprocess.run([sys.executable, "-c", probe], cwd=cwd, env=env, capture_output=True, text=True, check=True)
    return {Path(p).resolve().parent for p in out.stdout.split()}


def test_each_side_imports_its_own_code_and_the_old_way_is_caught(bench, tmp_path):
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                         check=True).stdout.strip()
    a = bench.export_revision(rev, str(tmp_path / "a"))
    b = bench.tree_site(str(tmp_path / "b"))
    neutral = tmp_path / "run"
    neutral.mkdir()

    # From a neutral folder (where the runner now starts each service): A runs the export, B this tree.
    assert imported_from(a, neutral) == {(tmp_path / "a" / "src" / part).resolve() for part in ("server", "solver")}
    assert imported_from(b, neutral) == {(ROOT / part).resolve() for part in ("server", "solver")}
    bench.check_imports(a, str(neutral))
    bench.check_imports(b, str(neutral))

    # From the repository's root (where the runner used to start them) the export is not what runs, and the
    # runner's check refuses to measure it.
    assert imported_from(a, ROOT) != imported_from(a, neutral)
    with pytest.raises(SystemExit, match="would not run the code asked for"):
        bench.check_imports(a, str(ROOT))
