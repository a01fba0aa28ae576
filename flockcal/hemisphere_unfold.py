"""Hemisphere flips undone in recorded positions: a Flock reports −p for a sensor outside its configured
hemisphere (docs/protocol.md §9), so a take recorded without tracking the hemisphere jumps through the
transmitter wherever a sensor crosses the boundary. `HemisphereUnfold` undoes that a chunk at a time.

Two kinds of continuity decide it. A sensor's own path: consecutive positions on opposite sides of the
transmitter (p·q < 0) can only be a crossing, as the driver judges live (`path_toggles`, shared with
drivers/checks.py). And the distances between sensors: a sensor that is mirrored from its first frame on
(it started outside the hemisphere) sits far from every neighbour, and only its mirror image sits where
its neighbours say. What neither can tell is which of the two mirror images of the whole performer is
the real one (the field is the same at p and −p); see `HemisphereUnfold` for that rule.
"""

from __future__ import annotations

import numpy as np

# Unit vector of each hemisphere in transmitter axes (x forward, z down): the half whose sign the bird
# forces positive (docs/protocol.md §9).
HEMISPHERE_VECTORS = {
    "forward": (1.0, 0.0, 0.0), "aft": (-1.0, 0.0, 0.0), "right": (0.0, 1.0, 0.0),
    "left": (0.0, -1.0, 0.0), "lower": (0.0, 0.0, 1.0), "upper": (0.0, 0.0, -1.0),
}

# A sensor unseen for longer than this may have crossed the boundary and come back (or crossed twice):
# its sign after the gap is decided again from the other sensors, not from its path.
GAP_S = 0.25
# How many shared frames (evenly spread) two sensors' distances are compared over, at most.
EVIDENCE_FRAMES = 256
# Two sensors' images agree or disagree only when being mirrored changes their distance by this much in
# the median frame: neighbours on a body differ by a metre or more, sensors near the transmitter by little.
EVIDENCE_MIN_M = 0.05
# Which of the two mirror images of a performer is real: the one in front of the transmitter (+x, the half
# the Flock's default forward hemisphere watches) when it holds this share of the sensor-frames there; a
# performer neither clearly in front nor behind (a transmitter overhead) is the image more in the
# recording's hemisphere.
DECISIVE_SHARE = 0.8
# Raw positions of a folding bird never read below zero along the hemisphere's axis; rounding may.
_FOLD_SLACK_M = 1e-6


def previous_valid(valid: np.ndarray) -> np.ndarray:
    """(n, m) row of each sensor's previous valid frame in the chunk, −1 when there is none."""
    n, m = valid.shape
    idx = np.where(valid, np.arange(n)[:, None], -1)
    last = np.maximum.accumulate(idx, axis=0)
    return np.vstack([np.full((1, m), -1), last[:-1]])


def path_toggles(positions: np.ndarray, valid: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each sensor's reported position jumps to the other side of the transmitter from its previous
    valid one (p·q < 0, a move that would have to pass through the transmitter: only a hemisphere flip does
    that), and each sensor's last valid raw position for the next chunk.

    positions (n, m, 3) raw (folded) positions, valid (n, m), last (m, 3) the last raw position before the
    chunk (NaN: none). Returns (toggles (n, m) bool, last (m, 3)).
    """
    p = np.asarray(positions, dtype=float)
    v = np.asarray(valid, dtype=bool)
    n, m = v.shape
    cols = np.arange(m)
    if v.all():  # the usual case: each sensor's previous position is the row above
        prev = np.concatenate([last[None], p[:-1]])
        new_last = p[-1].copy() if n else last
    else:
        prev_idx = previous_valid(v)
        prev = np.where((prev_idx >= 0)[..., None], p[np.maximum(prev_idx, 0), cols], last)
        seen = v.any(axis=0)
        last_row = n - 1 - np.argmax(v[::-1], axis=0)
        new_last = np.where(seen[:, None], p[last_row, cols], last)
    with np.errstate(invalid="ignore"):
        toggles = v & (np.einsum("nmi,nmi->nm", p, prev) < 0)
    return toggles, new_last


class HemisphereUnfold:
    """Undoes hemisphere flips in a take fed a chunk at a time (`feed`), state carried across chunks.

    Each sensor's positions are split into runs at gaps longer than GAP_S. Within a run a flip is where
    the path jumps through the transmitter (`path_toggles`). A run continuing from the last chunk keeps
    its sign; a new run (a sensor's first, or one after a gap) takes the sign that puts it where the
    sensors already placed are (the median change of distance between their two images over the shared
    frames, strongest pair first: a maximum spanning tree over the sensors). Runs that meet no placed
    sensor (the take's first chunk) are placed among themselves; if that group shows a flip at all (a
    crossing, or a sensor mirrored against the rest), which of its two mirror images is real is decided
    once: the one with DECISIVE_SHARE of its sensor-frames in front of the transmitter (+x), else the one
    with more of them in the recording's hemisphere (`hemisphere` given, or the one axis whose sign the raw
    positions never leave; without one, more in front). The field is the same at p and −p, so this is a
    convention, not a measurement: a performer mostly behind the transmitter, recorded in a hemisphere
    other than aft, comes out mirrored. A take without flips is returned as it came.

    Decisions rest on the chunk they are made in: feed chunks of a second or more (the commands use
    `CHUNK` frames). Counters: `frames_unfolded` (frames with a position mirrored back), `crossings`
    per sensor, `started_mirrored` (sensors outside the hemisphere from their first frame).
    """

    CHUNK = 4096

    def __init__(self, n_sensors: int, hemisphere: str | None = None):
        m = int(n_sensors)
        self.m = m
        self.hemisphere = None if hemisphere is None else np.array(HEMISPHERE_VECTORS[hemisphere])
        self.last_raw = np.full((m, 3), np.nan)
        self.last_time = np.full(m, -np.inf)
        self.mirrored = np.zeros(m, dtype=bool)  # whether the last raw position was mirrored
        self.placed = np.zeros(m, dtype=bool)
        self.frames_unfolded = 0
        self.crossings = np.zeros(m, dtype=int)
        self.started_mirrored = np.zeros(m, dtype=bool)

    def feed(self, times: np.ndarray, positions: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """The chunk's positions (n, m, 3) with every flip undone (the array given, when nothing was)."""
        p = np.asarray(positions, dtype=float)
        v = np.asarray(valid, dtype=bool)
        t = np.asarray(times, dtype=float)
        n, m = v.shape
        if n == 0:
            return p
        cols = np.arange(m)
        rows = np.arange(n)[:, None]
        prev_idx = previous_valid(v)
        prev_t = np.where(prev_idx >= 0, t[np.maximum(prev_idx, 0)], self.last_time[None, :])
        fresh = v & (t[:, None] - prev_t > GAP_S)  # a sensor's first frame, or its first after a gap
        toggles, last_raw = path_toggles(p, v, self.last_raw)
        toggles &= ~fresh
        # Flips within each run, counted from its start; the run before a chunk's first start continues.
        flips = np.cumsum(toggles, axis=0)
        start_row = np.maximum.accumulate(np.where(fresh, rows, -1), axis=0)
        base = np.where(start_row >= 0, flips[np.maximum(start_row, 0), cols], 0)
        odd = (flips - base) % 2 == 1
        carried = start_row < 0
        odd = np.where(carried, odd ^ self.mirrored, odd)

        run_rows, run_sensor = np.nonzero(fresh)
        if len(run_rows):
            sign = self._place_runs(p, v, odd, start_row, carried, run_rows, run_sensor, toggles)
            for r, b in zip(run_rows[sign].tolist(), run_sensor[sign].tolist()):
                odd[:, b] ^= start_row[:, b] == r
            self.started_mirrored[run_sensor[sign & ~self.placed[run_sensor]]] = True
        self.crossings += toggles.sum(axis=0)
        seen = v.any(axis=0)
        last_row = n - 1 - np.argmax(v[::-1], axis=0)
        self.mirrored = np.where(seen, odd[last_row, cols], self.mirrored)
        self.last_time = np.where(seen, t[last_row], self.last_time)
        self.last_raw = last_raw
        self.placed |= seen
        mirror = odd & v
        if not mirror.any():
            return p
        self.frames_unfolded += int(mirror.any(axis=1).sum())
        return np.where(mirror[..., None], -p, p)

    def _place_runs(self, p, v, odd, start_row, carried, run_rows, run_sensor, toggles) -> np.ndarray:
        """Whether each new run is mirrored at its start (see the class): a maximum spanning tree over the
        sensors' runs by how much their distances say, grown from the runs already placed."""
        u = np.where(odd[..., None], -p, p)  # every run as if its start were not mirrored
        # Nodes: the carried runs of placed sensors (fixed), then the new runs; frames of each.
        nodes = [(b, carried[:, b] & v[:, b]) for b in np.flatnonzero(self.placed & (carried & v).any(axis=0))]
        fixed = len(nodes)
        nodes += [(b, (start_row[:, b] == r) & v[:, b]) for r, b in zip(run_rows.tolist(), run_sensor.tolist())]
        N = len(nodes)
        evidence = _evidence(u, np.array([b for b, _ in nodes]), np.stack([f for _, f in nodes], axis=1), fixed)
        flip = np.zeros(N, dtype=bool)
        done = np.zeros(N, dtype=bool)
        done[:fixed] = True
        while not done.all():
            group = []
            if not done[:fixed].any() or not (np.abs(evidence[done][:, ~done]) > 0).any():
                # Nothing placed reaches the rest: start a group from its longest run.
                sizes = np.array([f.sum() for _, f in nodes])
                root = int(np.flatnonzero(~done)[np.argmax(sizes[~done])])
                done[root] = True
                group = [root]
            while True:
                w = np.where(done[:, None] & ~done[None, :], np.abs(evidence), 0.0)
                if not (w > 0).any():
                    break
                i, j = np.unravel_index(np.argmax(w), w.shape)
                flip[j] = flip[i] ^ (evidence[i, j] < 0)
                done[j] = True
                if group:
                    group.append(int(j))
            if group:
                flip[group] ^= self._mirror_image(p, u, v, nodes, group, flip, toggles)
        return flip[fixed:]

    def _mirror_image(self, p, u, v, nodes, group, flip, toggles) -> bool:
        """Whether a group of runs placed among themselves is to be mirrored as a whole (see the class)."""
        folded = any(flip[k] or toggles[nodes[k][1], nodes[k][0]].any() for k in group)
        if not folded:
            return False
        pts = np.concatenate([(-1.0 if flip[k] else 1.0) * u[nodes[k][1], nodes[k][0]] for k in group])
        front = float(np.mean(pts[:, 0] > 0))
        if front >= DECISIVE_SHARE or front <= 1.0 - DECISIVE_SHARE:
            return front < 0.5
        h = self.hemisphere if self.hemisphere is not None else folded_axis(p[v])
        inside = front if h is None else float(np.mean(pts @ h > 0))
        return inside < 0.5

    def summary(self, names) -> str | None:
        """One line on what was unfolded, or None when nothing was."""
        if not self.frames_unfolded:
            return None
        crossed = [f"{names[b]} ({c})" for b, c in enumerate(self.crossings.tolist()) if c]
        parts = [f"unfolded hemisphere flips in {self.frames_unfolded} frame(s)"]
        if crossed:
            parts.append("crossings: " + ", ".join(crossed))
        outside = [names[b] for b in np.flatnonzero(self.started_mirrored)]
        if outside:
            parts.append("outside the hemisphere from the start: " + ", ".join(outside))
        return "; ".join(parts)


def _evidence(u: np.ndarray, sensor: np.ndarray, member: np.ndarray, fixed: int) -> np.ndarray:
    """(N, N): for two runs (of sensors `sensor`, frames `member` (n, N)), how much nearer their positions
    `u` (n, m, 3) are as they stand than with one mirrored: the median over shared frames (up to
    EVIDENCE_FRAMES of each run's, evenly spread) of |a + b| − |a − b|; positive: same side. 0 where they
    share no frame, where it is below EVIDENCE_MIN_M, for two runs of one sensor and between the first
    `fixed` (placed already)."""
    pick = []
    for f in member.T:
        own = np.flatnonzero(f)
        pick.append(own[np.linspace(0, len(own) - 1, min(len(own), EVIDENCE_FRAMES)).astype(int)])
    rows = np.zeros(len(member), dtype=bool)
    rows[np.concatenate(pick)] = True
    rows = np.flatnonzero(rows)  # (not np.unique: its first call imports numpy.ma, 0.06 s)
    x = u[rows][:, sensor]  # (S, N, 3)
    both = member[rows][:, :, None] & member[rows][:, None, :]
    both &= (sensor[:, None] != sensor[None, :])[None]
    both[:, :fixed, :fixed] = False
    sq = np.einsum("sni,sni->sn", x, x)
    cross = 2.0 * np.einsum("sni,ski->snk", x, x)
    total = sq[:, :, None] + sq[:, None, :]
    gap = np.sqrt(np.maximum(total + cross, 0.0)) - np.sqrt(np.maximum(total - cross, 0.0))
    # Median over the shared frames: unshared ones sorted to the end as +inf.
    ranked = np.sort(np.where(both, gap, np.inf), axis=0)
    count = both.sum(axis=0)
    lo = np.take_along_axis(ranked, np.maximum((count - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(ranked, np.maximum(count // 2, 0)[None], axis=0)[0]
    with np.errstate(invalid="ignore"):
        median = np.where(count > 0, 0.5 * (lo + hi), 0.0)
    return np.where(np.abs(median) >= EVIDENCE_MIN_M, median, 0.0)


def folded_axis(positions: np.ndarray) -> np.ndarray | None:
    """The hemisphere a folding tracker reported in: the one axis and sign the raw positions (…, 3; NaN
    where invalid) never leave, as a unit vector; None when no axis or more than one qualifies."""
    x = np.asarray(positions, dtype=float).reshape(-1, 3)
    x = x[np.isfinite(x).all(axis=1)]
    if not len(x):
        return None
    lo, hi = x.min(axis=0), x.max(axis=0)
    found = [(k, 1.0) for k in range(3) if lo[k] >= -_FOLD_SLACK_M] + [(k, -1.0) for k in range(3) if hi[k] <= _FOLD_SLACK_M]
    if len(found) != 1:
        return None
    h = np.zeros(3)
    h[found[0][0]] = found[0][1]
    return h


def unfold_positions(times: np.ndarray, positions: np.ndarray, valid: np.ndarray, hemisphere: str | None = None
                     ) -> tuple[np.ndarray, HemisphereUnfold]:
    """(positions (n, m, 3) with the hemisphere flips undone — the array given when there were none, the
    `HemisphereUnfold` that did it, whose `summary` says what it did), fed `HemisphereUnfold.CHUNK` frames
    at a time, as every command that reads a take feeds it. `hemisphere`: the one the take was recorded
    in, if known (a .fobraw's stream setup); otherwise it is read off the raw positions."""
    v = np.asarray(valid, dtype=bool)
    unfold = HemisphereUnfold(v.shape[1], hemisphere)
    step = HemisphereUnfold.CHUNK
    parts = [unfold.feed(times[a:a + step], positions[a:a + step], v[a:a + step]) for a in range(0, len(v), step)]
    if not unfold.frames_unfolded:
        return positions, unfold
    return np.concatenate(parts), unfold


def unfold_take(take, hemisphere: str | None = None):
    """(`take` with its hemisphere flips undone — the same object when there were none, the
    `HemisphereUnfold` that did it): `unfold_positions` over the take's frames. A take read a chunk at a time
    (a `flockcal.take_files.TakeFile`: no `positions` array) is read once to find out, and comes back as an
    `UnfoldedTake` that unfolds each pass the same way (CHUNK frames at a time from its first)."""
    from dataclasses import replace

    if not hasattr(take, "positions"):
        from flockcal.take_files import UnfoldedTake

        unfold = HemisphereUnfold(len(take.names), hemisphere)
        for f in take.chunks(HemisphereUnfold.CHUNK):
            unfold.feed(f.times, f.positions, f.valid)
        return (UnfoldedTake(take, hemisphere) if unfold.frames_unfolded else take), unfold

    positions, unfold = unfold_positions(take.times, take.positions, take.valid, hemisphere)
    return (take if positions is take.positions else replace(take, positions=positions)), unfold
