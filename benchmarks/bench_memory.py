"""Peak memory of `flockcal convert` on a long recording and of `flockcal fit` (slip search, BVH and glTF) on a
long take, against the documented bound (3 × the input file + 150 MB) and, with --reference, against another
flockcal (e.g. the tree before chunked reading) on the same files.

Run: python benchmarks/bench_memory.py [--minutes 30] [--fit-minutes 20] [--reference /path/to/python]
Each command is a child process reporting its own peak resident memory, VmHWM, as it exits
(tests/peak_memory.py). Prints figures and ratios; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from peak_memory import run_flockcal  # noqa: E402

MB = 1e6


def run(python: str, argv: list, cwd: Path) -> tuple[int, float, float, str]:
    """(exit status, peak resident bytes, seconds, last stderr line) of `flockcal ARGV` run by `python`."""
    rc, err, peak, secs = run_flockcal(*argv, python=python, cwd=cwd)
    lines = err.strip().splitlines()
    return rc, peak, secs, lines[-1] if lines else ""


def report(label: str, path: Path, result, reference=None) -> None:
    rc, peak, secs, last = result
    size = path.stat().st_size
    bound = 3 * size + 150 * MB
    line = (f"{label:<8} input {size / MB:8.1f} MB  peak {peak / MB:8.1f} MB  = {peak / size:5.2f} × the file  "
            f"bound {bound / MB:8.1f} MB  peak/bound {peak / bound:5.2f}  {secs:6.1f} s  exit {rc}")
    if reference is not None:
        line += f"  | reference peak {reference[1] / MB:8.1f} MB ({reference[1] / size:5.2f} × the file), " \
                f"{reference[2]:6.1f} s; this/reference: peak {peak / reference[1]:5.2f}, time {secs / reference[2]:5.2f}"
    print(line, flush=True)
    if rc not in (0, 3):
        print(f"         {last}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=30.0, help="length of the recording to convert (16 sensors, 100 Hz)")
    ap.add_argument("--fit-minutes", type=float, default=20.0, help="length of the simulated take to fit (16 sensors, 100 Hz)")
    ap.add_argument("--reference", metavar="PYTHON", help="another interpreter whose `-m flockcal` to run on the same files")
    ap.add_argument("--keep", metavar="DIR", type=Path, help="make the files in DIR and keep them")
    args = ap.parse_args()

    from flockcal.simulator.fast_recording import write_recording
    from flockcal.simulator.smooth_source import SmoothSource

    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_memory."))
    work.mkdir(parents=True, exist_ok=True)
    me = sys.executable
    print(f"files in {work}; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)

    raw = work / "long.fobraw"
    if not raw.exists():
        t = time.monotonic()
        write_recording(raw, SmoothSource(16), 60 * args.minutes, 100.0)
        print(f"made {raw.name}: {args.minutes:g} min of 16 sensors at 100 Hz in {time.monotonic() - t:.0f} s")
    mine = run(me, ["convert", raw, "-o", work / "converted.npz"], work)
    ref = run(args.reference, ["convert", raw, "-o", work / "converted_ref.npz"], work) if args.reference else None
    report("convert", raw, mine, ref)

    take = work / "take.npz"
    if not take.exists():
        t = time.monotonic()
        made = subprocess.run([me, "-m", "flockcal", "simulate", "--motion", "exercise", "--seconds",
                               str(60 * args.fit_minutes), "--rate", "100", "--slip", "l_forearm@60:40:20", "-o",
                               str(take)], capture_output=True, text=True)
        if made.returncode:
            sys.exit(made.stderr)
        print(f"made {take.name}: {args.fit_minutes:g} min of 16 sensors at 100 Hz in {time.monotonic() - t:.0f} s")
    outputs = ["--json", "--bvh", work / "take.bvh", "--gltf", work / "take.glb"]
    mine = run(me, ["fit", take, *outputs], work)
    ref = run(args.reference, ["fit", take, "--json", "--bvh", work / "ref.bvh", "--gltf", work / "ref.glb"], work) \
        if args.reference else None
    report("fit", take, mine, ref)


if __name__ == "__main__":
    main()
