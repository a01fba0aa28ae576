"""Re-fit after a slip: the whole-take Gram plus, per slipped sensor, the Gram since its slip.

Detection comes a little after the slip, so cumulative snapshots of the whole-take accumulator are kept
at a few Hz; a segment is the whole minus the first snapshot taken at or after the slip (no frame from
before it). Pairs touching a slipped sensor are fitted on its segment, every other pair on all the data.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, fields, replace

import numpy as np

from flockcal.frames import Frames, chunk_frames, frames_of
from flockcal.solver.accumulator import BLOCK, GramAccumulator
from flockcal.solver.calibration import Bones, Calibration, calibrate
from flockcal.solver.calibration import joint_bones as _joint_bones
from flockcal.solver.errors import SolverError
from flockcal.solver.fits import TOLERANCE_M, JointEstimates, PairFits, joint_estimates, pair_fits


@dataclass
class Segment:
    """Frames of `sensor` since `start_s` (an event of `kind` "slip" or "swap")."""

    sensor: int
    start_s: float  # the event time
    kind: str
    base: GramAccumulator  # the whole take up to the first snapshot at or after start_s
    before: GramAccumulator | None  # the whole take up to the last snapshot at or before start_s
    base_s: float  # time of `base` (frames from here on are in the segment)
    # Fits on `before`, by pairs and tolerance: those frames never change, and the live service
    # searches the tree 30 times a second.
    _before_fits: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def before_fits(self, pairs: np.ndarray, tolerance: float) -> PairFits:
        """`pair_fits` of `pairs` on the frames before the segment (requires `before`), fitted once."""
        key = (np.ascontiguousarray(pairs).tobytes(), float(tolerance))
        fits = self._before_fits.get(key)
        if fits is None:
            fits = self._before_fits[key] = pair_fits(self.before, pairs, tolerance=tolerance)
        return fits


class SegmentedAccumulator:
    """A `GramAccumulator` over the whole take that also answers fits per segment after slips.

    `ingest(times, rotations, positions, valid)` feeds every frame once; `start_segment(sensor, time_s)`
    (or `apply(events)` with `SlipEvent`/`SwapEvent`s) opens a segment; `pair_fits(pairs)` fits each pair
    on the latest segment among its two sensors (after a slip: the frames since; after a swap: the
    frames before it, until the sensors are relabelled) and on the whole take otherwise.
    """

    def __init__(self, n_sensors: int, snapshot_hz: float = 10.0, history_s: float = 15.0, origin=None):
        if not snapshot_hz > 0 or not history_s > 0:
            raise SolverError("snapshot_hz and history_s must be positive")
        self.whole = GramAccumulator(n_sensors, origin=origin)
        self.n_sensors = int(n_sensors)
        self.snapshot_every = 1.0 / float(snapshot_hz)
        self._snaps: deque[tuple[float, GramAccumulator]] = deque(maxlen=max(2, int(np.ceil(history_s * snapshot_hz))))
        self._next_snap = None
        self.last_time = float("nan")
        self.segments: dict[int, Segment] = {}
        self.history: list[Segment] = []  # every segment ever opened, oldest first

    @property
    def frames(self) -> int:
        return self.whole.frames

    # -- the Accumulator protocol --------------------------------------------------------------------
    @property
    def whole_take(self) -> GramAccumulator:
        """The whole-take sums, every frame fed (segments are read from them)."""
        return self.whole

    def pair_view(self):
        """A GramAccumulator-like view whose pair statistics come from each pair's segment (the whole
        take while no segment is open)."""
        return SegmentView(self) if self.segments else self.whole

    def ingest(self, times, rotations, positions, valid=None) -> "SegmentedAccumulator":
        """Add a batch of frames (the `Accumulator` protocol's `ingest`); a snapshot is taken before the
        first frame at or after each grid time."""
        ts = np.atleast_1d(np.asarray(times, dtype=float))
        R = np.asarray(rotations, dtype=float)
        t = np.asarray(positions, dtype=float)
        if R.ndim == 3:
            R, t = R[None], t[None]
            valid = None if valid is None else np.asarray(valid)[None]
        if len(ts) != len(R):
            raise SolverError(f"{len(ts)} times for {len(R)} frames")
        if not len(ts):
            return self
        if self._next_snap is None:
            self._next_snap = ts[0]
        a = 0
        while a < len(ts):
            # Frames before the next grid time go in as one batch; then snapshot, then move the grid on.
            b = a + int(np.searchsorted(ts[a:], self._next_snap, side="left"))
            if b > a:
                self.whole.add_poses(R[a:b], t[a:b], None if valid is None else valid[a:b])
            if b < len(ts):
                self._snaps.append((float(ts[b]), self.whole.copy()))
                self._next_snap = max(self._next_snap + self.snapshot_every, ts[b] + 0.5 * self.snapshot_every)
            a = b
        self.last_time = float(ts[-1])
        return self

    def copy(self) -> "SegmentedAccumulator":
        """An independent copy (e.g. for a fit on another thread). Cheap: snapshots and segment bases
        never change once taken, so they are shared; only the whole-take sums are copied."""
        new = object.__new__(SegmentedAccumulator)
        new.__dict__.update(self.__dict__)
        new.whole = self.whole.copy()
        new._snaps = deque(self._snaps, maxlen=self._snaps.maxlen)
        new.segments = dict(self.segments)
        new.history = list(self.history)
        return new

    def start_segment(self, sensor: int, time_s: float, kind: str = "slip") -> Segment:
        """Open a new segment for `sensor` from `time_s` on (replacing any earlier one of that sensor)."""
        if not 0 <= int(sensor) < self.n_sensors:
            raise SolverError(f"sensor index {sensor} out of range 0..{self.n_sensors - 1}")
        after = [(s, a) for s, a in self._snaps if s >= time_s]
        before = [(s, a) for s, a in self._snaps if s <= time_s]
        if after:
            base_s, base = after[0]
        else:  # the slip is newer than the last snapshot: start from the next frame
            base_s, base = (self.last_time, self.whole.copy())
        seg = Segment(int(sensor), float(time_s), kind, base, before[-1][1] if before else None, base_s)
        self.segments[int(sensor)] = seg
        self.history.append(seg)
        return seg

    def apply(self, events) -> None:
        """Open segments for monitor events: a slip's sensor, or both sensors of a swap."""
        for ev in events:
            if getattr(ev, "kind", "slip") == "swap":
                for s in ev.sensor_indices:
                    self.start_segment(s, ev.time_s, "swap")
            else:
                self.start_segment(ev.sensor_index, ev.time_s, "slip")

    def since(self, sensor: int) -> GramAccumulator:
        """The frames of `sensor`'s current segment (the whole take when it has none)."""
        seg = self.segments.get(int(sensor))
        return self.whole.copy() if seg is None else self.segment_accumulator(seg)

    def segment_accumulator(self, seg: Segment) -> GramAccumulator:
        """The frames that belong to `seg` (after a swap: the frames before it)."""
        if seg.kind == "swap":
            # After a swap the sensors' data belongs to each other's bodies: keep what came before.
            return seg.before.copy() if seg.before is not None else GramAccumulator(self.n_sensors, origin=self.whole.origin)
        return self.whole - seg.base

    def pair_segments(self, pairs) -> list:
        """For each pair, the governing Segment (the later of its sensors' segments) or None."""
        return [self._pair_segment(i, j) for i, j in np.asarray(pairs, dtype=int).reshape(-1, 2).tolist()]

    def _pair_segment(self, i: int, j: int) -> Segment | None:
        a, b = self.segments.get(i), self.segments.get(j)
        if a is None or b is None:
            return a if b is None else b
        return b if b.start_s > a.start_s else a  # max() keeps the first of equals

    def accumulator_for(self, pair) -> GramAccumulator:
        seg = self.pair_segments([pair])[0]
        return self.whole if seg is None else self.segment_accumulator(seg)

    def joint_estimates(self, pairs, tolerance: float = TOLERANCE_M) -> JointEstimates:
        """`pair_fits(pairs).c` and `.l` alone (`fits.joint_estimates`), per pair on its segment: what the
        slip loop refits after every micro-batch."""
        P = np.asarray(pairs, dtype=int).reshape(-1, 2)
        parts, order = [], []
        for acc, rows in self._pair_groups(P):
            parts.append(joint_estimates(acc, P[rows], tolerance))
            order += rows
        if len(parts) == 1:
            return parts[0]
        inv = np.argsort(np.asarray(order))
        return JointEstimates(*(np.concatenate([getattr(e, f) for e in parts])[inv] for f in JointEstimates._fields))

    def _pair_groups(self, P: np.ndarray) -> list[tuple[GramAccumulator, list[int]]]:
        """(accumulator, rows of P) per governing segment, in order of first appearance."""
        segs = self.pair_segments(P)
        groups: dict[int, list[int]] = {}
        keyed: dict[int, Segment | None] = {}
        for k, s in enumerate(segs):
            groups.setdefault(id(s), []).append(k)
            keyed[id(s)] = s
        if not groups:
            return [(self.whole, [])]
        return [(self.whole if keyed[key] is None else self.segment_accumulator(keyed[key]), rows)
                for key, rows in groups.items()]

    def pair_fits(self, pairs, **options) -> PairFits:
        """`fits.pair_fits` per pair on its segment (see class docstring), in the order of `pairs`."""
        P = np.asarray(pairs, dtype=int).reshape(-1, 2)
        groups = self._pair_groups(P)
        if len(groups) == 1:
            return pair_fits(groups[0][0], P, **options)
        parts, order = [], []
        for acc, rows in groups:
            parts.append(pair_fits(acc, P[rows], **options))
            order += rows
        inv = np.argsort(np.asarray(order))
        return PairFits(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])[inv] for f in fields(PairFits)})

    def calibration(self, hierarchy=None, root=None, names=None, slip_events=None,
                    tolerance: float = TOLERANCE_M) -> Calibration:
        """The whole-take calibration, with every joint and bone that involves a segmented sensor taken
        from a calibration of that segment (same tree), marked with the segment's start."""
        fits = self.tree_fits(tolerance) if hierarchy is None and self.segments else None
        whole = calibrate(self.whole, hierarchy=hierarchy, root=root, names=names, tolerance=tolerance, fits=fits)
        whole = replace(whole, slip_events=tuple(slip_events or ()))
        if not self.segments:
            return whole
        tree = whole.parent_map()
        jc, jp = whole.joint_child, whole.joint_parent
        segs = self.pair_segments(np.stack([jc, jp], axis=1))
        start = np.full(len(jc), np.nan)
        joints, placement = whole.joints, whole.placement.copy()
        hinge_rule = None if whole.hinge_point is None else whole.hinge_point.rule.copy()
        hinge_share = None if whole.hinge_point is None else whole.hinge_point.data_share.copy()
        done: dict[int, Calibration] = {}
        for k, seg in enumerate(segs):
            if seg is None:
                continue
            if id(seg) not in done:
                done[id(seg)] = calibrate(self.segment_accumulator(seg), hierarchy=tree, root=whole.names[whole.root],
                                          names=names, tolerance=tolerance)
            start[k] = seg.start_s
        for key, part in done.items():
            mine = [k for k, s in enumerate(segs) if s is not None and id(s) == key]
            theirs = [int(np.flatnonzero(part.joint_child == jc[k])[0]) for k in mine]
            joints = _rows_from(joints, mine, part.joints, theirs)
            placement[jc[mine]] = part.joints.c[theirs]
            if hinge_rule is not None and part.hinge_point is not None:
                hinge_rule[mine] = part.hinge_point.rule[theirs]
                hinge_share[mine] = part.hinge_point.data_share[theirs]
        hinge_point = None if hinge_rule is None else replace(whole.hinge_point, rule=hinge_rule, data_share=hinge_share)
        cal = replace(whole, joints=joints, placement=placement, segment_start_s=start, hinge_point=hinge_point)
        return replace(cal, bones=_bones_after(cal, start, self))

    def tree_fits(self, tolerance: float = TOLERANCE_M) -> PairFits:
        """All pairs fitted on the whole take, for the tree search, with each pair that touches a slipped
        sensor judged by its residual rms pooled over the placement before the slip and the one after,
        each fitted on its own frames. A slip moves a sensor on its body, not to another body: a
        whole-take fit blends the two placements, its residual grows with the step, and the tree would
        re-link the slipped sensor's neighbours elsewhere until the new segment outweighs the old."""
        fits = pair_fits(self.whole, tolerance=tolerance)
        segs = self.pair_segments(fits.pairs)
        rms = fits.rms.copy()
        for seg in {id(s): s for s in segs if s is not None and s.kind == "slip"}.values():
            rows = np.flatnonzero([s is seg for s in segs])
            after = pair_fits(self.segment_accumulator(seg), fits.pairs[rows], tolerance=tolerance)
            n, sq = after.n.astype(float), after.n * np.nan_to_num(after.rms, posinf=0.0) ** 2
            if seg.before is not None:
                before = seg.before_fits(fits.pairs[rows], tolerance)
                n, sq = n + before.n, sq + before.n * np.nan_to_num(before.rms, posinf=0.0) ** 2
            with np.errstate(invalid="ignore", divide="ignore"):
                rms[rows] = np.where(n > 0, np.sqrt(sq / n), fits.rms[rows])
        return replace(fits, rms=rms)


def _rows_from(fits: PairFits, rows, other: PairFits, other_rows) -> PairFits:
    """`fits` with its `rows` replaced by `other`'s `other_rows` (same pairs, another segment's data)."""
    out = {}
    for f in fields(PairFits):
        a = getattr(fits, f.name).copy()
        a[rows] = getattr(other, f.name)[other_rows]
        out[f.name] = a
    return PairFits(**out)


def _bones_after(cal: Calibration, start: np.ndarray, seg: SegmentedAccumulator) -> Bones:
    """The bones of `cal`'s joints as they stand (each from its own segment or the whole take), so a bone is
    the distance between the joint centres the result reports; marked with the latest segment start among
    its two joints (`start`, per joint row; NaN: the whole take).

    Taken from the segment's own calibration instead, a bone mixed two fits: after a hand slipped, the
    forearm bone held the segment's (or, its elbow undetermined there, the whole take's) length while the
    elbow came from the whole take and the wrist from the segment, 0.2–2 mm apart, and the skeleton file
    of such a fit was refused as hand-edited."""
    b = _joint_bones(seg.pair_view(), cal)
    row_of = np.full(cal.n_sensors, -1)
    row_of[cal.joint_child] = np.arange(len(cal.joint_child))
    return replace(b, segment_start_s=np.fmax(start[row_of[b.from_joint]], start[row_of[b.to_joint]]))


class SegmentView:
    """A SegmentedAccumulator seen as one GramAccumulator whose pair statistics come from each pair's
    segment (after a slip: the frames since it), so a known-skeleton fit refits a slipped sensor's
    joints on its new placement while the saved bones stay as they are."""

    def __init__(self, seg):
        self._seg = seg
        self.whole = seg.whole

    def __getattr__(self, name):
        return getattr(self.whole, name)

    def _grouped(self, pairs, method: str):
        P = np.asarray(pairs, dtype=int).reshape(-1, 2)
        segs = self._seg.pair_segments(P)
        groups: dict[int, list[int]] = {}
        keyed = {}
        for k, s in enumerate(segs):
            groups.setdefault(id(s), []).append(k)
            keyed[id(s)] = s
        out = None
        for key, rows in groups.items():
            s = keyed[key]
            acc = self.whole if s is None else self._seg.segment_accumulator(s)
            part = getattr(acc, method)(P[rows])
            single = not isinstance(part, tuple)
            parts = (part,) if single else part
            if out is None:
                out = [np.empty((len(P),) + np.shape(x)[1:], dtype=np.result_type(x)) for x in parts]
            for o, x in zip(out, parts):
                o[rows] = x
        if out is None:
            return getattr(self.whole, method)(P)
        return out[0] if len(out) == 1 and method == "translation_power" else tuple(out)

    def normal_equations(self, pairs):
        return self._grouped(pairs, "normal_equations")

    def translation_power(self, pairs):
        return self._grouped(pairs, "translation_power")

    def block_moments(self, pairs):
        return self._grouped(pairs, "block_moments")

    def pair_point(self, point, src, dst) -> np.ndarray:
        """`GramAccumulator.pair_point` with each (src, dst) pair on its segment (a rigid member's bones)."""
        x = np.asarray(point, dtype=float).reshape(-1, 3)
        P = np.stack([np.asarray(src, dtype=int).reshape(-1), np.asarray(dst, dtype=int).reshape(-1)], axis=1)
        out = np.full((len(P), 3), np.nan)
        for acc, rows in self._seg._pair_groups(P):
            out[rows] = acc.pair_point(x[rows], P[rows, 0], P[rows, 1])
        return out

    def relative_rotation(self, src, dst) -> np.ndarray:
        """`GramAccumulator.relative_rotation` with each (src, dst) pair on its segment."""
        P = np.stack([np.asarray(src, dtype=int).reshape(-1), np.asarray(dst, dtype=int).reshape(-1)], axis=1)
        out = np.full((len(P), 3, 3), np.nan)
        for acc, rows in self._seg._pair_groups(P):
            out[rows] = acc.relative_rotation(P[rows, 0], P[rows, 1])
        return out


def segmented_from_take(take, events, piece: int | None = None) -> SegmentedAccumulator:
    """A SegmentedAccumulator over a whole recorded take, with a segment opened at each slip event
    (`take` as for `detect_slips`: a take file is read `piece` frames at a time, by default about 8 MB of
    arrays; `events` from it, or stored events with time_s and sensor_index)."""
    m = len(take.names) if getattr(take, "names", None) is not None else np.shape(take.rotations)[1]
    piece = piece or chunk_frames(m)
    seg = SegmentedAccumulator(m)
    seg._snaps = deque()  # offline: keep a snapshot at every event time, however far apart
    cuts = sorted({float(e.time_s) for e in events})
    feed = _SegmentFeed(seg.whole, piece)
    k, last = 0, float("nan")
    for f in frames_of(take, piece):
        a = 0
        while k < len(cuts):  # the cuts inside this chunk (the first frame at or after each)
            b = int(np.searchsorted(f.times, cuts[k], side="left"))
            if b >= len(f):
                break
            feed.add(f[a:b])
            feed.end()
            seg._snaps.append((cuts[k], seg.whole.copy()))
            a, k = b, k + 1
        feed.add(f[a:])
        if len(f):
            last = float(f.times[-1])
    feed.end()
    for c in cuts[k:]:  # slips at or after the last frame
        seg._snaps.append((c, seg.whole.copy()))
    seg.last_time = last
    seg.apply(sorted(events, key=lambda e: e.time_s))
    return seg


class _SegmentFeed:
    """Hands one segment's frames to an accumulator in pieces, making the same `add_poses` blocks as one call
    with the whole segment would: pieces of `piece` frames (a multiple of the accumulator's block) from the
    segment's start, the last one longer than a block, so none of it waits in the accumulator's pending
    block to be summed with the next segment's frames."""

    def __init__(self, acc, piece: int):
        self.acc = acc
        self.piece = max(BLOCK, piece // BLOCK * BLOCK)
        self.held: list = []
        self.count = 0

    def add(self, frames) -> None:
        if not len(frames):
            return
        self.held.append(frames)
        self.count += len(frames)
        if self.count <= self.piece + BLOCK:
            return
        whole, a = Frames.concat(self.held, frames.n_sensors), 0
        while self.count - a > self.piece + BLOCK:
            self._put(whole[a:a + self.piece])
            a += self.piece
        rest = whole[a:]  # copied, so the concatenation is not kept alive by a view of its tail
        self.held = [Frames(*(np.array(getattr(rest, k)) for k in ("times", "rotations", "positions", "valid")))]
        self.count = len(rest)

    def end(self) -> None:
        if self.held:
            self._put(Frames.concat(self.held, self.held[0].n_sensors))
        self.held, self.count = [], 0

    def _put(self, f) -> None:
        if len(f):
            self.acc.add_poses(f.rotations, f.positions, f.valid)
