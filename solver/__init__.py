"""Solver: the incremental all-pairs Gram accumulator, joint fits, topology, bones, slippage.

Pure numpy/scipy; no I/O, and it never imports the driver or the server.
"""
