"""The BLAS routine the accumulator sums Grams with (dsyrk), without importing scipy.linalg: that package's
start-up (scipy's array-API layer pulls in numpy.f2py, numpy.testing and numpy.random) cost every
`flockcal fit` ~0.1 s for one function. `dsyrk` is scipy.linalg.blas.dsyrk itself, the same object.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os


def _fblas():
    """scipy's Fortran BLAS wrappers (scipy/linalg/_fblas), loaded from their extension file alone; the
    module scipy.linalg.blas re-exports (`scipy.linalg.blas.dsyrk is scipy.linalg._fblas.dsyrk`). Falls back
    to the ordinary import where the file is not where scipy keeps it."""
    spec = importlib.util.find_spec("scipy")  # where scipy is, without running its __init__ (0.01–0.02 s)
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    folder = os.path.join(roots[0], "linalg") if roots else ""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES if folder else ():
        path = os.path.join(folder, "_fblas" + suffix)
        if os.path.exists(path):
            loader = importlib.machinery.ExtensionFileLoader("scipy.linalg._fblas", path)
            spec = importlib.util.spec_from_file_location("scipy.linalg._fblas", path, loader=loader)
            if spec is not None:
                module = importlib.util.module_from_spec(spec)
                loader.exec_module(module)
                return module
    from scipy.linalg import _fblas

    return _fblas


dsyrk = _fblas().dsyrk
