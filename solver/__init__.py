"""Solver: the incremental all-pairs Gram accumulator, joint fits, topology, bones, slippage.

Pure numpy/scipy; no I/O, and it never imports the driver or the server.
"""

from flockcal.lazy import public_api

# What a user of the solver reaches for, each loaded on first use (tests/test_public_api.py resolves them).
__getattr__, __dir__, __all__ = public_api(__name__, {
    "fit": "flockcal.solver.take_fit",
    "Calibration": "flockcal.solver.calibration",
    "Bones": "flockcal.solver.calibration",
    "calibrate": "flockcal.solver.calibration",
    "solve": "flockcal.solver.solve",  # named as its module: imported with the package (flockcal/lazy.py)
    "solve_take": "flockcal.solver.solve",
    "GramAccumulator": "flockcal.solver.accumulator",
    "SegmentedAccumulator": "flockcal.solver.segments",
    "PairFits": "flockcal.solver.fits",
    "pair_fits": "flockcal.solver.fits",
    "SlipMonitor": "flockcal.solver.slippage.monitor",
    "SlipEvent": "flockcal.solver.slippage.monitor",
    "SwapEvent": "flockcal.solver.slippage.monitor",
    "detect_slips": "flockcal.solver.slippage.monitor",
    "SlipWatch": "flockcal.solver.slippage.watch",
    "LiveCalibration": "flockcal.solver.live",
    "Humanoid": "flockcal.solver.humanoid",
    "find_humanoid": "flockcal.solver.humanoid",
    "Articulation": "flockcal.solver.reconstruct",
    "articulation": "flockcal.solver.reconstruct",
    "Skeleton": "flockcal.solver.known_skeleton",
    "calibration_from_json": "flockcal.solver.calibration_json",
    "Progress": "flockcal.solver.progress",
    "progress_of": "flockcal.solver.progress",
    "fit_markers": "flockcal.solver.optical.pipeline",
    "OpticalFit": "flockcal.solver.optical.pipeline",
    "rigid_pair_scale": "flockcal.solver.scale",
    "SolverError": "flockcal.solver.errors",
})
