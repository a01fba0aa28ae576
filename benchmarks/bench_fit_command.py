"""`flockcal fit TAKE --json` as a user runs it — a fresh process, start-up included — on a 30 s, 16-sensor,
144 Hz take (docs/performance.md: ≤ 1 s median on a quiet machine), against the reference implementation
of the same job in the same run: benchmarks/reference_fit.py (the paper's per-pair SVD over every pair and
a minimum spanning tree, numpy only, also a fresh process). The two run in turn, A B A B …, so the ratio
holds while the machine's load drifts.

    python benchmarks/bench_fit_command.py [--runs 7] [--baseline "python -m flockcal"]

Each figure is the median over the runs of the child's wall time and its CPU time (user + system, the
kernel's accounting of the finished process: robust to load in a way wall time is not), with the load
average. --baseline adds another flockcal (another checkout's interpreter, say) as a third command, with
its ratio to this one. Also: `flockcal --help`, and where the fit's import time goes (python -X importtime).
Prints figures and ratios; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RATE, SECONDS, TARGET_S = 144.0, 30.0, 1.0


def timed(argv: list[str]) -> tuple[float, float]:
    """(wall seconds, user + system CPU seconds) of one run of `argv` as a child process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{shlex.join(argv)} exited with {proc.returncode}")
    return wall, usage.ru_utime + usage.ru_stime


def in_turn(commands: dict[str, list[str]], runs: int) -> dict[str, list[tuple[float, float]]]:
    """Every command once unmeasured, then `runs` rounds of each in turn."""
    for argv in commands.values():
        timed(argv)
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in commands}
    for _ in range(runs):
        for k, argv in commands.items():
            out[k].append(timed(argv))
    return out


def import_seconds(argv: list[str]) -> dict[str, float]:
    """Seconds of import time by top-level package (each module's own time, python -X importtime)."""
    done = subprocess.run([sys.executable, "-X", "importtime", *argv[1:]], capture_output=True, text=True)
    total: dict[str, float] = {}
    for line in done.stderr.splitlines():
        fields = line.removeprefix("import time:").split("|")
        if not line.startswith("import time:") or len(fields) != 3 or not fields[0].strip().isdigit():
            continue
        top = fields[2].strip().split(".")[0]
        total[top] = total.get(top, 0.0) + int(fields[0]) / 1e6
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--baseline", help='another flockcal to time beside this one, e.g. "/other/venv/bin/python -m flockcal"')
    args = ap.parse_args()
    flockcal = [sys.executable, "-m", "flockcal"]
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        take = str(Path(tmp) / "take.npz")
        subprocess.run(flockcal + ["simulate", "--motion", "exercise", "--seconds", str(SECONDS), "--rate", str(RATE),
                                   "--birds", "16", "--seed", "1", "-o", take], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        commands = {"flockcal fit": flockcal + ["fit", take, "--json"],
                    "reference": [sys.executable, str(HERE / "reference_fit.py"), take]}
        if args.baseline:
            commands["baseline fit"] = shlex.split(args.baseline) + ["fit", take, "--json"]
        got = in_turn(commands, args.runs)
        helps = in_turn({"help": flockcal + ["--help"]}, args.runs)["help"]
        imports = import_seconds(commands["flockcal fit"])
    load1 = os.getloadavg()

    def med(k: str, i: int) -> float:
        return statistics.median(x[i] for x in got[k])

    def ratio(a: str, b: str, i: int) -> float:
        return statistics.median(x[i] / y[i] for x, y in zip(got[a], got[b]))

    print(f"flockcal fit, {SECONDS:g} s x 16 sensors at {RATE:g} Hz (exercise, default soft tissue), {args.runs} runs "
          f"in turn, fresh processes; load average {load0[0]:.1f} before, {load1[0]:.1f} after")
    for k in commands:
        print(f"  {k + ':':<15} median {med(k, 0):.2f} s wall, {med(k, 1):.2f} s CPU (user + system)")
    print(f"  flockcal --help: median {statistics.median(x[0] for x in helps):.2f} s wall, "
          f"{statistics.median(x[1] for x in helps):.2f} s CPU")
    print(f"  ratio flockcal fit / reference: {ratio('flockcal fit', 'reference', 1):.2f} CPU, "
          f"{ratio('flockcal fit', 'reference', 0):.2f} wall (median of the runs' ratios)")
    if args.baseline:
        print(f"  ratio flockcal fit / baseline: {ratio('flockcal fit', 'baseline fit', 1):.2f} CPU, "
              f"{ratio('flockcal fit', 'baseline fit', 0):.2f} wall")
    print(f"  against the {TARGET_S:g} s target: {med('flockcal fit', 0) / TARGET_S:.2f} (wall), "
          f"{med('flockcal fit', 1) / TARGET_S:.2f} (CPU: what a quiet machine's wall time comes to)")
    top = sorted(imports.items(), key=lambda kv: -kv[1])[:6]
    print(f"  import time of the fit ({sum(imports.values()):.2f} s): " + ", ".join(f"{k} {v:.2f} s" for k, v in top))


if __name__ == "__main__":
    main()
