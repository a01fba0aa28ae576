"""The public API (issue 49): `import flockcal; flockcal.fit(flockcal.load_take(path))`.

Every name a package's `__all__` lists resolves, to what its table says; `import flockcal` loads no numpy
and no other layer; `flockcal.fit` is the path `flockcal fit` runs, to the byte of its `--json`; the
top-level names carry numpydoc docstrings whose examples run.
"""

from __future__ import annotations

import doctest
import importlib
import json
import re
import subprocess
import sys

import numpy as np
import pytest

import flockcal
from flockcal.frames import Frames
from flockcal.simulator.take import simulate
from flockcal.takes import Take, save_take

PACKAGES = ["flockcal", "flockcal.solver", "flockcal.drivers", "flockcal.simulator", "flockcal.server",
            "flockcal.exports"]
LAYERS = ("flockcal.solver", "flockcal.server", "flockcal.drivers", "flockcal.simulator", "flockcal.commands",
          "flockcal.exports")


def loaded_after(code: str) -> list[str]:
    """The modules a fresh interpreter holds after running `code`."""
    probe = f"{code}\nimport sys, json\nprint(json.dumps(sorted(sys.modules)), file=sys.stderr)"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode in (0, 2), done.stderr  # 2: `--help` without a command exits so
    return json.loads(done.stderr.strip().splitlines()[-1])


def test_import_flockcal_loads_no_numpy_and_no_other_layer():
    loaded = loaded_after("import flockcal; assert 'fit' in dir(flockcal) and flockcal.__version__")
    assert "flockcal" in loaded
    heavy = [m for m in loaded if m.split(".")[0] in ("numpy", "scipy") or m.startswith(LAYERS)]
    assert not heavy, heavy


def test_help_loads_neither_scipy_nor_any_layer_a_command_runs():
    # `flockcal --help` registers every command; each imports its layer inside its `func`. (numpy itself is
    # loaded today by commands/takecheck.py and commands/batch_tasks.py at module level: notes/h49api.md.)
    loaded = loaded_after("from flockcal.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass")
    below = tuple(x for x in LAYERS if x != "flockcal.commands")
    heavy = [m for m in loaded if m.split(".")[0] == "scipy" or m.startswith(below)]
    assert not heavy, heavy


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_resolves_and_dir_lists_it(package):
    # Tried: every name of each package's `__all__`, in a fresh interpreter (a name is loaded on first use, so
    # one that resolves only because another test imported its module would hide a wrong table).
    code = (f"import importlib\np = importlib.import_module({package!r})\n"
            "missing = [n for n in p.__all__ if n not in dir(p)]\n"
            "assert not missing, missing\n"
            "for n in p.__all__:\n    getattr(p, n)\n")
    loaded_after(code)
    mod = importlib.import_module(package)
    assert len(mod.__all__) == len(set(mod.__all__)) >= 1
    for name in mod.__all__:
        obj = getattr(mod, name)
        assert getattr(obj, "__module__", "").startswith("flockcal"), (name, obj)
        assert getattr(obj, "__name__", name) == name, (name, obj)  # the thing, not its module
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        getattr(mod, "no_such_name")


def test_a_name_spelled_like_its_module_is_the_function():
    # flockcal.solver.solve is a submodule too: importing it sets the package's attribute to the module.
    import flockcal.solver.solve  # noqa: F401
    from flockcal import solver

    assert callable(solver.solve) and solver.solve.__name__ == "solve"
    assert solver.fit is flockcal.fit


SECTION = re.compile(r"^ {4}(\w[\w ]*)\n {4}-{3,}$", re.M)


@pytest.mark.parametrize("name", flockcal.__all__)
def test_top_level_names_have_numpydoc_sections_and_examples_that_run(name):
    obj = getattr(flockcal, name)
    doc = obj.__doc__ or ""
    sections = set(SECTION.findall(doc))
    assert "Examples" in sections, (name, sections)
    if isinstance(obj, type):
        assert sections & {"Attributes", "Parameters"}, (name, sections)
    else:
        assert {"Parameters", "Raises"} <= sections, (name, sections)
        returns_none = obj.__annotations__.get("return") in (None, "None")
        assert returns_none or "Returns" in sections, (name, sections)
    tests = doctest.DocTestFinder(recurse=False).find(obj, name, globs={})
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for test in tests:
        result = runner.run(test, out=lambda text: pytest.fail(f"{name}'s example:\n{text}"))
        assert result.attempted >= 2 and not result.failed


@pytest.fixture(scope="module")
def slipped_take(tmp_path_factory):
    # A take whose fit finds a slip, so the API runs the whole path: accumulate, solve, search, re-solve.
    take, truth = simulate("human", "exercise", seconds=30, birds=6, seed=2, sta_mm=0,
                           faults={"slip": {"sensor": "l_forearm", "at_time": 18.0, "distance_m": 0.03}})
    path = tmp_path_factory.mktemp("api") / "slipped.npz"
    save_take(path, take)
    return path, take, truth


def fit_json(path, *options) -> str:
    done = subprocess.run([sys.executable, "-m", "flockcal", "fit", str(path), "--json", *map(str, options)],
                          capture_output=True, text=True, timeout=280)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_fit_is_what_fit_json_prints_slips_and_all(slipped_take):
    path, _, _ = slipped_take
    cal = flockcal.fit(flockcal.load_take(path))
    assert [e.sensor for e in cal.slip_events] == ["l_forearm"] and np.isfinite(cal.segment_start_s).any()  # re-fitted
    assert json.dumps(cal.to_dict(), indent=2) + "\n" == fit_json(path)


def test_fit_options_are_fits_options(slipped_take, tmp_path):
    path, take, truth = slipped_take
    hierarchy = tmp_path / "tree.json"
    hierarchy.write_text(json.dumps(truth["parent"]))
    cal = flockcal.fit(take, hierarchy=truth["parent"], root="pelvis", tolerance=0.008, slips=False)
    assert cal.slip_events == () and cal.hierarchy_given
    assert json.dumps(cal.to_dict(), indent=2) + "\n" == fit_json(path, "--hierarchy", hierarchy, "--root", "pelvis",
                                                                  "--tolerance-mm", 8, "--no-slips")


class Chunked:
    """A take that hands out its frames a chunk at a time and nothing else (a `ChunkedTake`)."""

    def __init__(self, take: Take):
        self._take, self.names, self.rate_hz = take, take.names, take.rate_hz
        self.asked: list[int] = []

    @property
    def n_frames(self) -> int:
        return self._take.n_frames

    def chunks(self, size=None):
        self.asked.append(size)
        for f in self._take.chunks(size):
            yield Frames(f.times.copy(), f.rotations.copy(), f.positions.copy(), f.valid.copy())


def test_fit_reads_a_chunked_take_and_refuses_a_path(slipped_take):
    path, take, _ = slipped_take
    chunked = Chunked(take)
    # The whole fit reads chunks: the accumulation, the humanoid's sample, the slip search and the re-fit
    # after the slip (flockcal/take_files.py streams takes this way), each asking for a size.
    assert json.dumps(flockcal.fit(chunked).to_dict()) == json.dumps(flockcal.fit(take).to_dict())
    assert chunked.asked and all(size for size in chunked.asked)
    with pytest.raises(TypeError, match=r"flockcal.load_take\(path\)"):
        flockcal.fit(str(path))
    with pytest.raises(flockcal.FlockcalError, match="no_such_sensor"):
        flockcal.fit(take, root="no_such_sensor")
    assert np.isfinite(flockcal.fit(take, slips=False).c).all()
