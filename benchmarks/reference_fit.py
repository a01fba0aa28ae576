"""The reference implementation of fitting a take, as a command (the yardstick of bench_fit_command.py):
the paper's per-pair solve (tests/reference.py: the stacked 3n×6 system and its SVD) for every pair of
sensors, and the minimum spanning tree over the pairs' rms (Kruskal's), printed as JSON.

    python benchmarks/reference_fit.py TAKE.npz

No Gram matrix, no noise model, no slip scan, no hinge rule: what a textbook program does with the same
file, in a fresh process of its own (numpy only), so both sides pay Python's start-up.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from reference import reference_pair_fit  # noqa: E402


def main(path: str) -> None:
    with np.load(path, allow_pickle=False) as z:
        R, t = z["rotations"], z["positions"]
        valid = z["valid"] if "valid" in z.files else np.ones(R.shape[:2], dtype=bool)
        names = [str(x) for x in z["names"]] if "names" in z.files else [str(i) for i in range(R.shape[1])]
    m = R.shape[1]
    fits = {}
    for i in range(m):
        for j in range(i + 1, m):
            fits[i, j] = reference_pair_fit(R[:, i], t[:, i], R[:, j], t[:, j], valid[:, i] & valid[:, j])
    root = list(range(m))

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    joints = []
    for (i, j), f in sorted(fits.items(), key=lambda kv: kv[1].rms):
        a, b = find(i), find(j)
        if a != b:
            root[a] = b
            joints.append({"a": names[i], "b": names[j], "c": f.c.tolist(), "l": f.l.tolist(), "rms_m": f.rms,
                           "rank": f.rank})
    json.dump({"sensors": names, "joints": joints}, sys.stdout, indent=2)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main(sys.argv[1])
