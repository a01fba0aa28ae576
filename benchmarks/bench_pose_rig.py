"""Cost of the pose message's `rig` (issue 34, item 2: under 1 % of a core at a 15 Hz client): the time
to build and serialise it (server.pose.rig_pose) for a 16-sensor fitted performer, and the whole message's;
and the rig file the pages fetch to draw it (`/gltf?rest=sensor&animation=false`, flockcal.exports.gltf.glb_chunks
from a frame log), which a page fetches at most every 2 s during a live session. Prints figures, asserts nothing.

    python benchmarks/bench_pose_rig.py [--calls 7000]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from flockcal.server import pose
from flockcal.exports.gltf import glb_chunks
from flockcal.server.downloads import FrameFile
from flockcal.server.framelog import FrameLog
from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.solver.reconstruct import reconstruct


def per_call(fn, calls: int, repeats: int = 7) -> float:
    """Best of `repeats` blocks of `calls`: the machine is shared, and the least-disturbed block is the cost."""
    fn()  # caches (the drawing layout) warm, as for a live client
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls // repeats):
            fn()
        best = min(best, (time.perf_counter() - start) / (calls // repeats))
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=7000)
    args = ap.parse_args()
    take, _ = simulate("human", "exercise", seconds=20, rate_hz=100, seed=1, birds=16)
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    cal = calibrate(acc, names=list(take.names))
    k = take.n_frames // 2
    frame = (list(take.names), take.rotations[k], take.positions[k], take.valid[k])
    whole = per_call(lambda: json.dumps(pose.live_pose(*frame, cal)), args.calls)
    layout = pose._cache[2]  # the drawing layout live_pose cached for this fit
    rec = reconstruct(take.rotations[k][None], take.positions[k][None], layout.art)
    # What the rig adds to each message, timed by itself: a difference of two whole-message times on a
    # shared machine is mostly noise.
    extra = per_call(lambda: json.dumps(pose.rig_pose(rec, layout)), args.calls)
    size = len(json.dumps(pose.rig_pose(rec, layout)))
    print(f"pose message (16 sensors, built + JSON, rig included): {whole * 1e3:.3f} ms; the rig (built + JSON): "
          f"{extra * 1e3:.3f} ms, {size} bytes")
    print(f"at a 15 Hz client: {15 * extra * 100:.2f} % of a core for the rig (target < 1 %), "
          f"{15 * whole * 100:.2f} % for the whole pose message")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "take.frames"
        log = FrameLog(path, list(take.names), take.rate_hz)
        log.write(take.times, take.rotations, take.positions, take.valid)
        log.close()
        frames, result = FrameFile(path), cal.to_dict()
        rig_file = lambda: b"".join(glb_chunks(result, frames, rest="sensor", animation=False))  # noqa: E731
        each = per_call(rig_file, 70)
        print(f"the pages' rig file (16 bodies): {len(rig_file()) / 1e3:.0f} kB built in {each * 1e3:.1f} ms; "
              f"one page fetching it every 2 s: {each / 2 * 100:.2f} % of a core")


if __name__ == "__main__":
    main()
