"""The base layer (flockcal's shared basics) imports no other layer: every layer may stand on it.

Each base module is imported in a fresh interpreter, and the modules it pulled in are checked: none of
the solver, server, drivers, simulator, CLI commands or exports may be among them.
"""

import json
import subprocess
import sys

import pytest

BASE = ["errors", "takes", "atomic", "threads", "frames", "markers", "bars", "skeleton", "names"]
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
