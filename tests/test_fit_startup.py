"""`flockcal fit` within a second (issue #50): what it must not import, and the stand-ins that let it skip
those imports giving numpy's and scipy's own values. The time itself is measured by
benchmarks/bench_fit_command.py, not here.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flockcal.simulator.take import simulate
from flockcal.takes import save_take

# What a plain `fit --json` once paid for without using (CPU seconds at start-up, load ~8 on the shared
# machine): scipy.spatial (BVH export's rotations and a saved skeleton's fit: 0.3 s), scipy.linalg (one
# BLAS routine: 0.15 s), scipy.sparse (a tree's connected components: 0.05 s), numpy.ma (np.unique's and
# np.median's first call: 0.05 s), tqdm where no bar is drawn (0.05–0.08 s).
NOT_NEEDED = ("scipy.spatial", "scipy.linalg", "scipy.sparse", "scipy.stats", "numpy.ma", "tqdm")


def test_a_plain_fit_imports_none_of_the_modules_it_does_not_use(tmp_path):
    take, _ = simulate("human", "exercise", seconds=12, rate_hz=60, seed=3, sta_mm=0)
    save_take(tmp_path / "take.npz", take)
    probe = ("import sys, json\nfrom flockcal.cli import main\n"
             f"code = main(['fit', {str(tmp_path / 'take.npz')!r}, '--json'])\n"
             "sys.stdout.flush()\n"
             f"print(json.dumps([x for x in {NOT_NEEDED!r} if x in sys.modules]), file=sys.stderr)\n"
             "sys.exit(code)\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["joints"]  # it did fit
    assert json.loads(done.stderr.strip().splitlines()[-1]) == []


def test_the_accumulators_dsyrk_is_scipys():
    # solver/blas.py loads it from scipy's extension file without importing scipy.linalg; it must be the
    # very routine scipy.linalg.blas gives, so every Gram (and `fit --json`) stays what it was.
    import scipy.linalg.blas

    from flockcal.solver.blas import dsyrk

    x = np.random.default_rng(0).normal(size=(300, 40))
    np.testing.assert_array_equal(dsyrk(1.0, x.T, trans=0), scipy.linalg.blas.dsyrk(1.0, x.T, trans=0))


@settings(max_examples=300, deadline=None)
@given(st.integers(1, 40), st.integers(1, 5), st.integers(0, 2**16), st.floats(0.0, 0.3), st.floats(0.0, 1.0))
def test_column_median_is_numpys_median_and_nanmedian_to_the_bit(n, k, seed, holes, kept):
    import warnings

    from flockcal.solver.slippage.stats import column_median

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, k)) * 10.0 ** rng.integers(-3, 3)
    x[rng.random((n, k)) < holes] = np.nan
    mask = rng.random((n, k)) < kept
    np.testing.assert_array_equal(column_median(x), np.median(x, axis=0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN column: NaN, as column_median gives
        want = np.nanmedian(np.where(mask, x, np.nan), axis=0)
    np.testing.assert_array_equal(column_median(x, mask), want)


@given(st.lists(st.integers(0, 40), max_size=30))
def test_present_is_numpys_unique(values):
    from flockcal.solver.slippage.stats import present

    x = np.array(values, dtype=np.intp)
    np.testing.assert_array_equal(present(x), np.unique(x))


@given(st.lists(st.tuples(st.integers(0, 20), st.integers(0, 20)), max_size=25), st.lists(st.integers(0, 25), max_size=6))
def test_touching_is_numpys_isin_over_a_joints_ends(joints, sensors):
    from flockcal.solver.slippage.stats import touching

    J = np.array(joints, dtype=np.intp).reshape(-1, 2)
    np.testing.assert_array_equal(touching(J, sensors), np.isin(J, sensors).any(axis=1))
