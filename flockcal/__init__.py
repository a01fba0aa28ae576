"""flockcal: live skeleton calibration for 6-DOF magnetic motion trackers.

The public API, for scripts and notebooks::

    import flockcal
    cal = flockcal.fit(flockcal.load_take("take.npz"))
    cal.to_dict()  # the object `flockcal fit --json` prints

The names below load on first use (`import flockcal` itself loads no numpy). The parts live in
flockcal.solver, flockcal.simulator, flockcal.drivers, flockcal.server and flockcal.exports, each with
its own `__all__`; this package holds the command line, the take interchange and the shared basics.
"""

from flockcal.lazy import public_api

__version__ = "0.1.0"

# Each public name and the module that defines it: strings, so this package imports none of them (the base
# layer imports no other layer, tests/test_base_layer.py) until one is asked for.
__getattr__, __dir__, __all__ = public_api(__name__, {
    "fit": "flockcal.solver.take_fit",
    "Calibration": "flockcal.solver.calibration",
    "Take": "flockcal.takes",
    "load_take": "flockcal.takes",
    "save_take": "flockcal.takes",
    "make_take": "flockcal.takes",
    "simulate": "flockcal.simulator.take",
    "FlockcalError": "flockcal.errors",
})
