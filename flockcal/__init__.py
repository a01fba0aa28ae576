"""flockcal: live skeleton calibration for 6-DOF magnetic motion trackers.

The distribution's top-level package: it holds the command line and the .npz take interchange;
the work lives in flockcal.solver, flockcal.simulator, flockcal.drivers and flockcal.server.
"""

__version__ = "0.1.0"
