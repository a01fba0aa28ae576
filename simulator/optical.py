"""The simulator's optical mode: skin markers fixed in the bone frames of a BodyModel, seen by cameras.

2–4 markers per body, soft tissue (each marker sliding over its bone with the neighbouring joints' angles,
the sensor path's rule in soft_tissue.py), Gaussian marker noise, occlusion gaps (NaN runs) and label swaps
between two markers over a span of frames; plus the paper's three-rod rig with universal joints. Truth (which body
each marker rides, joint-to-joint bone lengths, the parent map) comes back beside the take.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from flockcal.markers import MarkerTake, make_marker_take
from flockcal.simulator.body import BodyModel, SimulatorError, bone_poses, by_name
from flockcal.rotations import axis_angle, from_rotvec


def place_markers(model: BodyModel, per_body=(2, 4), seed: int = 0, standoff=(0.03, 0.07)):
    """Marker layout: (body (k,) int, offsets (k,3) in the bone frame, names (k,) str).

    Markers sit between a body's inboard joint and the far end of the body (its outboard joint, or a
    point past the joint for a leaf), `standoff` metres off that axis like a marker on the skin.
    `per_body` is (low, high) inclusive, or a list with one count per body.
    """
    rng = np.random.default_rng([int(seed), 0x0971])
    m = model.m
    counts = (
        np.asarray(per_body, dtype=int)
        if np.ndim(per_body) and len(per_body) == m and m != 2
        else rng.integers(per_body[0], per_body[1] + 1, m)
    )
    body, offsets, names = [], [], []
    for i in range(m):
        far = body_axis(model, i)
        axis = far / max(np.linalg.norm(far), 1e-9)
        for j in range(int(counts[i])):
            along = rng.uniform(0.15, 0.85) * far
            radial = rng.normal(size=3)
            radial -= radial.dot(axis) * axis
            radial /= max(np.linalg.norm(radial), 1e-9)
            offsets.append(along + rng.uniform(*standoff) * radial)
            body.append(i)
            names.append(f"{model.names[i]}_{j + 1}")
    return np.array(body), np.array(offsets), tuple(names)


def body_axis(model: BodyModel, i: int) -> np.ndarray:
    """From body i's inboard joint to its far end (its outboard joints' mean, or a point past the joint
    for a leaf), in the bone frame: the line its markers sit along."""
    kids = model.children(i)
    if kids:
        return np.mean([model.joint_offset[k] for k in kids], axis=0)
    # A leaf continues its parent's joint direction for a typical hand/foot/head length.
    d = model.joint_offset[i] if model.parent[i] >= 0 else np.array([0, 0, 1.0])
    far = 0.6 * d if np.linalg.norm(d) > 1e-6 else np.array([0.0, 0.0, 0.1])
    return far / max(np.linalg.norm(far), 1e-9) * np.clip(np.linalg.norm(far), 0.08, 0.25)


def skin_normals(model: BodyModel, body: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(k, 3) each marker's outward skin normal in its bone frame: its offset's part across the body's axis."""
    out = np.zeros((len(body), 3))
    for j, (i, off) in enumerate(zip(body, offsets)):
        a = body_axis(model, int(i))
        a = a / max(np.linalg.norm(a), 1e-9)
        r = off - off.dot(a) * a
        out[j] = r / max(np.linalg.norm(r), 1e-9)
    return out


def marker_positions(B: np.ndarray, b: np.ndarray, body: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Exact world marker positions (n, k, 3) from bone poses B (n,m,3,3), b (n,m,3)."""
    return np.einsum("nkij,kj->nki", B[:, body], offsets) + b[:, body]


def add_noise(markers: np.ndarray, sigma_m: float, seed: int = 0) -> np.ndarray:
    """Isotropic Gaussian noise of `sigma_m` metres per coordinate."""
    rng = np.random.default_rng([int(seed), 0x401])
    return markers + rng.normal(scale=sigma_m, size=markers.shape)


def occlude(markers: np.ndarray, fraction: float, rate_hz: float, seed: int = 0, mean_gap_s: float = 0.25) -> np.ndarray:
    """NaN gaps: each marker loses about `fraction` of its frames in runs of ~`mean_gap_s` seconds."""
    out = markers.copy()
    n, k, _ = out.shape
    if fraction <= 0:
        return out
    rng = np.random.default_rng([int(seed), 0x0CC])
    gap = max(1, int(round(mean_gap_s * rate_hz)))
    runs = max(1, int(round(fraction * n / gap)))
    starts = rng.integers(0, n, (k, runs))
    lengths = rng.integers(max(1, gap // 2), 2 * gap, (k, runs))
    frame = np.arange(n)
    hidden = ((frame[None, None, :] >= starts[..., None]) & (frame[None, None, :] < (starts + lengths)[..., None])).any(1)
    out[hidden.T] = np.nan
    return out


def swap_labels(markers: np.ndarray, swaps) -> np.ndarray:
    """Exchange the labels of markers a and b over frames [start, stop) for each (start, stop, a, b)."""
    out = markers.copy()
    for start, stop, a, b in swaps:
        out[start:stop, [a, b]] = out[start:stop, [b, a]]
    return out


def random_swaps(body: np.ndarray, markers: np.ndarray, n_swaps: int, rate_hz: float, seed: int = 0, span_s=(0.3, 1.0)):
    """`n_swaps` swaps between markers of adjacent-looking bodies that pass close to each other."""
    rng = np.random.default_rng([int(seed), 0x5A9])
    n, k, _ = markers.shape
    d = np.nanmean(np.linalg.norm(markers[:, :, None] - markers[:, None], axis=-1), axis=0)
    d[body[:, None] == body[None, :]] = np.inf
    out = []
    for _ in range(n_swaps):
        a = int(rng.integers(k))
        b = int(np.argmin(d[a]))
        length = int(rng.uniform(*span_s) * rate_hz)
        start = int(rng.integers(n // 5, max(n // 5 + 1, n - length - n // 5)))
        out.append((start, start + length, a, b))
    return out


def smooth_local_rotations(model: BodyModel, seconds: float, rate_hz: float, seed: int = 0, amplitude: float = 0.8,
                           with_coordinates: bool = False):
    """A generic exercise: every joint sweeps its range with a few incommensurate sinusoids.

    Returns (local rotations (n,m,3,3), root translation (n,3), times (n,)), plus the joint coordinates
    (n, m, 3) soft tissue follows when `with_coordinates`. Used when the motion library's named routines
    are not wanted (rods, tests); ball joints move about all three axes.
    """
    rng = np.random.default_rng([int(seed), 0x5E0])
    n = max(2, int(round(seconds * rate_hz)))
    times = np.arange(n) / rate_hz
    m = model.m
    freq = rng.uniform(0.15, 0.7, (m, 3, 3))
    phase = rng.uniform(0, 2 * np.pi, (m, 3, 3))
    wave = np.sin(2 * np.pi * freq[None] * times[:, None, None, None] + phase[None]).mean(-1) * 1.6  # (n, m, 3)
    lo, hi = model.limits[..., 0], model.limits[..., 1]
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * amplitude
    coords = mid[None] + half[None] * np.clip(wave, -1, 1)
    L = np.empty((n, m, 3, 3))
    for i in range(m):
        kind = model.joint_type[i]
        if kind == "hinge":
            L[:, i] = axis_angle(np.broadcast_to(model.hinge_axis[i], (n, 3)), coords[:, i, 0])
        elif kind == "ball":
            L[:, i] = from_rotvec(coords[:, i])
        else:
            L[:, i] = np.eye(3)
    root = model.root
    root_rv = np.stack([0.5 * np.sin(0.31 * times + 1), 0.4 * np.sin(0.23 * times), 1.2 * np.sin(0.11 * times + 2)], 1)
    L[:, root] = model.home_rotation @ from_rotvec(root_rv)
    trans = model.home_position + 0.3 * np.stack([np.sin(0.2 * times), np.sin(0.13 * times + 1), 0.1 * np.sin(0.5 * times)], 1)
    return (L, trans, times, coords) if with_coordinates else (L, trans, times)


def rods(lengths=(0.45, 0.50, 0.45), seed: int = 0) -> BodyModel:
    """The paper's rig: aluminium rods end to end, joined by universal joints (two axes, no twist).

    Rod k runs along its +Y from its inboard joint; the universal joint turns about the parent's X and
    Z axes only, which `rod_motion` respects.
    """
    base = by_name("linkage", seed=seed)
    m = len(lengths)
    lengths = np.asarray(lengths, dtype=float)
    model = base.subset(base.names[:m])
    off = np.zeros((m, 3))
    off[1:, 1] = lengths[:-1]
    limits = np.zeros((m, 3, 2))
    limits[1:, 0] = (-1.0, 1.0)
    limits[1:, 2] = (-1.0, 1.0)
    names = tuple(f"rod{k}" for k in range(m))
    return replace(
        model, names=names, joint_offset=off, limits=limits, kind="rods", extra={"rod_lengths_m": lengths.tolist()}
    )


def rod_motion(model: BodyModel, seconds: float, rate_hz: float, seed: int = 0):
    """Universal-joint motion for `rods`: local rotation Rx(α) Rz(γ), no twist about the rod."""
    L, trans, times = smooth_local_rotations(model, seconds, rate_hz, seed, amplitude=0.9)
    rng = np.random.default_rng([int(seed), 0x0D5])
    n = len(times)
    for i in range(model.m):
        if model.parent[i] < 0:
            continue
        f = rng.uniform(0.2, 0.6, 2)
        ph = rng.uniform(0, 2 * np.pi, 2)
        a = np.sin(2 * np.pi * f[0] * times + ph[0]) * 0.9
        g = np.sin(2 * np.pi * f[1] * times + ph[1]) * 0.9
        ex, ez = np.broadcast_to([1.0, 0, 0], (n, 3)), np.broadcast_to([0, 0, 1.0], (n, 3))
        L[:, i] = axis_angle(ex, a) @ axis_angle(ez, g)
    return L, trans, times


def simulate_markers(
    model: str | BodyModel = "human",
    motion: str | tuple | None = None,
    seconds: float = 10.0,
    rate_hz: float = 60.0,
    seed: int = 0,
    per_body=(2, 4),
    noise_m: float = 0.001,
    occlusion: float = 0.0,
    n_swaps: int = 0,
    sta_mm: float = 0.0,
) -> tuple[MarkerTake, dict]:
    """A marker take and its truth.

    `motion`: None for `smooth_local_rotations`, a routine name for `flockcal.simulator.motion.routine`,
    or a (local rotations, root translation, times[, joint coordinates]) tuple. `sta_mm`: soft tissue, the
    largest slide of each marker over its bone from one joint (soft_tissue.py's rule; needs the joint
    coordinates, so a tuple motion must carry them). Truth: the model's `truth()` plus "marker_body"
    {marker: body}, "marker_offset" {marker: [x,y,z] bone frame, at rest}, "swaps" [(start, stop, a, b)],
    "soft_tissue" {"size_mm", "seed"}.
    """
    if isinstance(model, str):
        model = by_name(model, seed=seed)
    q = None
    if motion is None:
        L, root_t, times, q = smooth_local_rotations(model, seconds, rate_hz, seed, with_coordinates=True)
    elif isinstance(motion, str):
        from flockcal.simulator import motion as motion_lib

        mo = motion_lib.routine(model, motion, seconds, rate_hz, seed)
        L, root_t, q = mo.pose(mo.times)
        times = mo.times
    else:
        L, root_t, times = motion[:3]
        q = motion[3] if len(motion) > 3 else None
    B, b = bone_poses(model, L, root_t)
    body, offsets, names = place_markers(model, per_body, seed)
    if sta_mm > 0:
        if q is None:
            raise SimulatorError("soft tissue follows the joint angles: give the motion's joint coordinates too")
        from flockcal.simulator.soft_tissue import SoftTissue

        sta = SoftTissue.for_sites(model, body, skin_normals(model, body, offsets), sta_mm, seed, stream=0x0A57)
        exact = np.einsum("nkij,nkj->nki", B[:, body], offsets[None] + sta.slides(q)) + b[:, body]
    else:
        exact = marker_positions(B, b, body, offsets)
    swaps = random_swaps(body, exact, n_swaps, rate_hz, seed) if n_swaps else []
    obs = add_noise(exact, noise_m, seed) if noise_m > 0 else exact.copy()
    obs = occlude(obs, occlusion, rate_hz, seed)
    obs = swap_labels(obs, swaps)
    if not np.isfinite(obs).any(axis=(1, 2)).all():
        raise SimulatorError("the occlusion left frames with no marker at all; lower the occlusion fraction")
    # The simulator's world is the Flock's transmitter frame, z down.
    take = make_marker_take(obs, names, rate_hz, times=times, source="simulated optical take", up="-z",
                            up_from="the simulator (the Flock's frame)")
    truth = model.truth()
    truth.update(
        marker_body={nm: model.names[i] for nm, i in zip(names, body)},
        marker_offset={nm: o.tolist() for nm, o in zip(names, offsets)},
        swaps=[(int(s), int(e), names[a], names[c]) for s, e, a, c in swaps],
        soft_tissue={"size_mm": float(sta_mm), "seed": int(seed)},
    )
    return take, truth
