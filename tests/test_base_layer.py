"""The layers stand on each other without a cycle, and the base layer (flockcal's shared basics) imports
no other layer: every layer may stand on it.

Statically: the import graph of every module (every import statement, in functions and under
TYPE_CHECKING too: tests/layers.py) has no cycle between the layers docs/internals.md defines. At run time:
each base module is imported in a fresh interpreter, and none of the solver, server, drivers, simulator,
CLI commands or exports may be among the modules it pulled in.
"""

import json
import subprocess
import sys

import pytest

from layers import ROOT, import_edges, layer_cycles

# Every module of flockcal/ but the command line's (the commands layer).
BASE = sorted(p.stem for p in (ROOT / "flockcal").glob("*.py") if p.stem not in ("__init__", "__main__", "cli"))
LAYERS = ("flockcal.solver", "flockcal.server", "flockcal.drivers", "flockcal.simulator", "flockcal.commands",
          "flockcal.exports", "flockcal.cli")


@pytest.mark.parametrize("module", BASE)
def test_base_module_imports_no_other_layer(module):
    code = (f"import json, sys; import flockcal.{module}; "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('flockcal'))))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout)
    assert f"flockcal.{module}" in loaded  # the check looked at the right interpreter
    above = [m for m in loaded if m.startswith(LAYERS)]
    assert not above, f"flockcal.{module} imports {', '.join(above)}"


def test_no_cycle_between_layers():
    edges = import_edges()
    cycles = layer_cycles(edges)
    why = [f"{a} → {b}: {'; '.join(edges[a, b][:3])}" for group in cycles for a, b in edges if a in group and b in group]
    assert not cycles, f"layers that import each other round a cycle {cycles}:\n" + "\n".join(why)
    assert not [b for a, b in edges if a == "base"], edges  # the base layer imports no other layer at all


def test_the_checker_finds_a_cycle_made_in_a_function_or_for_an_annotation(tmp_path):
    # Tried: a base module that imports the solver only inside a function, one that imports it only under
    # TYPE_CHECKING, and one by a relative import from a subpackage: each closes a cycle with the solver's
    # import of the base layer. The same tree without them has none.
    def package(files: dict[str, str]):
        for rel, text in files.items():
            (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / rel).write_text(text)
        return import_edges({"flockcal": "flockcal", "flockcal.solver": "solver"}, tmp_path)

    clean = {"flockcal/__init__.py": "", "flockcal/errors.py": "", "solver/__init__.py": "",
             "solver/fits.py": "from flockcal.errors import *\n"}
    assert layer_cycles(package(clean)) == []
    for source in ("def f():\n    from flockcal.solver.fits import x\n",
                   "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from flockcal.solver import fits\n"):
        (tmp_path / "flockcal" / "late.py").write_text(source)
        assert layer_cycles(package(clean)) == [["base", "solver"]], source
        (tmp_path / "flockcal" / "late.py").unlink()
    (tmp_path / "flockcal" / "sub").mkdir()
    edges = package({**clean, "flockcal/sub/__init__.py": "", "flockcal/sub/up.py": "from ..solver import fits\n"})
    assert layer_cycles(edges) == [["base", "solver"]]
    assert edges["base", "solver"] == ["flockcal.sub.up imports flockcal.solver.fits"]
