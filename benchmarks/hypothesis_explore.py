"""Runs the property tests with many fresh random examples (the "explore" Hypothesis profile of
tests/conftest.py) — the nightly-style search CI does not do, since CI runs fixed examples.

    python benchmarks/hypothesis_explore.py [--examples 400] [pytest args…]

A failure prints the falsifying example and a `@reproduce_failure` blob to paste into the test.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROPERTY_TESTS = ["tests/test_solver_accumulator.py", "tests/test_solver_fits.py", "tests/test_solver_topology.py"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=400, help="examples per property test (default 400; CI runs 15)")
    args, rest = ap.parse_known_args(argv)
    env = dict(os.environ, FLOCKCAL_HYPOTHESIS_PROFILE="explore", FLOCKCAL_EXAMPLES=str(args.examples))
    t0 = time.perf_counter()
    rc = subprocess.call([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          *PROPERTY_TESTS, *rest], cwd=ROOT, env=env)  # fmt: skip
    print(f"explored {args.examples} examples per property test in {time.perf_counter() - t0:.0f} s: "
          f"{'no counterexample' if rc == 0 else 'FAILED, see above'}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
