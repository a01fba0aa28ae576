"""Segmentation of skin markers into rigid bodies: soft tissue tolerated, still groups kept whole, the
linkage the same as scipy's, bad input refused."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flockcal.solver.optical.segmentation import SegmentationError, distance_ranges, linkage_labels, segment_markers


def hinge_take(n=600, sta_m=0.0, third_still=False, seed=0):
    """Two bodies swinging ±60° about a hinge at the origin, 5 markers each (plus, optionally, a third
    body of 4 markers bolted to the first). Soft tissue: each marker slides up to `sta_m` along its own
    direction with the joint angle, as skin over a bone does (0 at rest, full at the ends of the range)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    angle = np.radians(60) * np.sin(2 * np.pi * 0.4 * t)
    wobble = Rotation.from_rotvec(np.stack([0.3 * np.sin(0.7 * t), 0.2 * np.cos(0.5 * t), 0.1 * t], axis=1))
    a = rng.normal(size=(5, 3)) * 0.05 + [0, 0, 0.25]
    b = rng.normal(size=(5, 3)) * 0.05 + [0, 0, -0.25]
    Rb = Rotation.from_rotvec(np.outer(angle, [1, 0, 0]))
    A = np.stack([wobble.apply(p) for p in a], axis=1)
    B = np.stack([(wobble * Rb).apply(p) for p in b], axis=1)
    parts = [A, B]
    if third_still:
        c = rng.normal(size=(4, 3)) * 0.05 + [0.2, 0, 0.3]
        parts.append(np.stack([wobble.apply(p) for p in c], axis=1))
    M = np.concatenate(parts, axis=1) + [0.0, 0.0, 1.0]
    k = M.shape[1]
    dirs = rng.normal(size=(k, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    M = M + sta_m * (np.abs(angle) / angle.max())[:, None, None] * dirs[None]
    M = M + rng.normal(size=M.shape) * 0.0005
    truth = np.array([0] * 5 + [1] * 5 + ([0] * 4 if third_still else []))
    return M, truth


def partition(labels):
    return {tuple(np.flatnonzero(labels == g)) for g in np.unique(labels)}


def test_soft_tissue_of_8mm_a_marker_does_not_split_a_segment():
    # 8 mm a marker in independent directions: two markers move up to 16 mm against each other, about the
    # 12 mm the knee trial's thigh cluster shows; the claim is the 15 mm tolerance (docs/optical.md)
    M, truth = hinge_take(sta_m=0.008)
    seg = segment_markers(M)
    assert partition(seg.labels) == partition(truth)
    assert seg.internal_motion.max() < seg.tolerance_m


def test_a_group_that_never_moved_against_a_body_is_one_body_with_it():
    M, truth = hinge_take(sta_m=0.005, third_still=True)
    seg = segment_markers(M)
    assert partition(seg.labels) == partition(truth)


def test_a_tolerance_below_the_soft_tissue_splits_and_the_count_can_be_forced():
    M, truth = hinge_take(sta_m=0.008)
    assert segment_markers(M, tolerance=0.002).n_groups > 2  # tried: a noise-level tolerance on skin markers
    assert partition(segment_markers(M, tolerance=0.002, n_groups=2).labels) == partition(truth)


def test_average_linkage_cut_matches_scipy():
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    M, _ = hinge_take(sta_m=0.012, third_still=True, seed=3)
    R = distance_ranges(M[::5])
    Z = linkage(squareform(R, checks=False), method="average")
    for tol in (0.005, 0.01, 0.02, 0.05):
        assert partition(linkage_labels(R, tol)) == partition(fcluster(Z, tol, criterion="distance"))
    for g in (2, 3, 5):
        assert partition(linkage_labels(R, 1.0, n_groups=g)) == partition(fcluster(Z, g, criterion="maxclust"))


def test_gaps_count_as_unseen_not_as_motion():
    M, truth = hinge_take(sta_m=0.008)
    rng = np.random.default_rng(1)
    M[rng.random(M.shape[:2]) < 0.05] = np.nan  # 5 % of marker-frames missing
    assert partition(segment_markers(M).labels) == partition(truth)


def test_bad_input_is_refused_with_a_clear_error():
    with pytest.raises(SegmentationError, match="at least two markers"):  # tried: one marker
        segment_markers(np.zeros((10, 1, 3)))
    with pytest.raises(SegmentationError, match="shape"):  # tried: 2-D positions
        segment_markers(np.zeros((10, 3)))
    with pytest.raises(SegmentationError, match="positive"):  # tried: a zero tolerance
        segment_markers(np.zeros((10, 4, 3)), tolerance=0.0)


def test_cli_refuses_a_negative_rigid_tolerance_in_one_line(tmp_path):
    from flockcal.markers import make_marker_take, save_markers

    M, _ = hinge_take()
    save_markers(tmp_path / "m.npz", make_marker_take(M, [f"m{i}" for i in range(M.shape[1])], 100.0))
    # tried: --rigid-mm -3
    proc = subprocess.run([sys.executable, "-m", "flockcal", "fit-markers", str(tmp_path / "m.npz"), "--rigid-mm", "-3"],
                          check=False, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--rigid-mm" in lines[0]


def test_every_body_of_a_noisy_occluded_simulated_human_is_recovered():
    from flockcal.simulator import optical as so

    # 2–4 markers a body, 1 mm noise, 3 % occlusion gaps, every joint moving: 16 bodies, none mixed
    take, truth = so.simulate_markers("human", seconds=12, rate_hz=60, seed=2, noise_m=0.001, occlusion=0.03)
    body = np.unique([truth["marker_body"][m] for m in take.marker_names], return_inverse=True)[1]
    seg = segment_markers(take.markers)
    assert seg.n_groups == 16
    assert partition(seg.labels) == partition(body)


def test_label_swaps_in_part_of_the_take_do_not_split_bodies():
    from flockcal.simulator import optical as so

    # two swaps of 5–7 % of the frames each, on different bodies (docs/optical.md: swaps covering over a
    # tenth of one body's frames can split it)
    take, truth = so.simulate_markers("human", seconds=12, rate_hz=60, seed=2, noise_m=0.001, occlusion=0.02,
                                      n_swaps=2, per_body=(3, 4))  # fmt: skip
    assert truth["swaps"]
    body = np.unique([truth["marker_body"][m] for m in take.marker_names], return_inverse=True)[1]
    assert partition(segment_markers(take.markers).labels) == partition(body)
