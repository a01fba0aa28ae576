"""The live humanoid streams, VRPN (server/vrpn.py) and VMC (server/vmc.py): their work done at the pipeline
thread's steps (`Outputs.hand_over`, from the frames the reader queued), their sockets on a thread of their own
("fc-outputs"), which also stands in while the pipeline does not come by. No socket ever blocks (docs/server.md).
"""

from __future__ import annotations

import collections
import errno
import logging
import selectors
import socket
import threading
from typing import Callable

import numpy as np

from flockcal.clock import Clock
from flockcal.errors import FlockcalError
from flockcal.frames import Frames
from flockcal.rotations import as_quat
from flockcal.server import vmc, vrpn
from flockcal.solver.humanoid import BONES, Humanoid
from flockcal.solver.humanoid_pose import HumanoidRig, humanoid_rig
from flockcal.solver.reconstruct import held_poses
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

# A live session's next fit reaches the streams' rig at most this often (fits come 30 times a second; a rebuild
# costs about 1.5 ms of the pipeline thread in the service: at 0.2 s they were 0.8 points of a core).
RIG_REFRESH_S = 0.5
HUMANOID_REFRESH_S = 5.0  # the humanoid is found again this often, and whenever the tree changes
RETRY_S = 1.0  # a stopped session's fit that gave no rig (too few frames yet) is tried again this often
SAMPLE_S, SAMPLE_FRAMES = 0.1, 600  # the frames the humanoid is found from: one every 0.1 s, the last minute
TRACKING_S = 0.25  # newer frames than this, every bone's sensor valid: VMC's tracking status is OK
OSC_GRACE_S = 0.02  # how long a due VMC bundle waits for a hand-over that sends frames, to ride on it
# VMC bundles go one a hand-over, at least half a period apart, each stamped with its own tick: a tick that
# waited for frames is caught up by the next hand-overs (they come 64-72 times a second), not skipped. A
# sender held up for OSC_BEHIND periods skips what it missed rather than sending a burst.
OSC_SPACING, OSC_BEHIND = 0.5, 3
# While a VRPN client takes every frame, they go out two at a time, not each: a hand-over's work costs about
# as much for two frames as for one (docs/streams.md), so a frame waits at most for the next one, one frame
# period (6.9 ms at 144 Hz). A frame more than PAIR_S after the one before (a slower tracker, the frame after
# a gap) goes at once; a lone frame before a pause goes within STALL_S.
PAIR_S, STALL_S = 0.008, 0.02
# The pipeline's thread does the streams' work at its steps (it wakes for every batch anyway: a thread of
# their own woken for it cost a point of a core more). When it has not come by for STAND_IN_S (a session's
# stop holding it up, or no pipeline at all), the streams' own thread does the same work, woken by the
# reader's hand-overs as the pipeline is.
STAND_IN_S = 0.25
LOOK_S = 0.1  # frames no stream sends yet are taken this often all the same: held, sampled, the fit followed
QUEUE_BATCHES = 256  # batches waiting for the streams at most (the oldest go first: live streams want the newest)


def humanoid_of(fit, sample: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Humanoid:
    """Which body is which humanoid bone: the one place the streams ask. The fit the service published
    carries it (found by the fit thread from the session's sample); a fit without one that can pose a rig
    (read back from a stored §5 result) has it found here from a sample of the live frames."""
    hum = getattr(fit, "humanoid", None)
    if hum is not None and hum.posable:
        return hum
    from flockcal.solver.humanoid import find_humanoid

    return find_humanoid(fit, *sample)


class Outputs:
    """VRPN and VMC out, as `settings` ask (`vrpn_port`, `osc_targets`, `osc_hz`). Built before the service
    serves: a port in use or a receiver that cannot be resolved is one line in `lines` (what `serve` prints)
    and the service runs without that output. `feed` (the reader's thread) only queues; `hand_over` (the
    pipeline's thread, at each step) does the streams' work; `start` / `stop` run their own thread (the
    sockets; the work while the pipeline does not come by). `clock`: the service's (the frames' times, the
    streams' cadence, VRPN's wall times)."""

    def __init__(self, settings, names: tuple[str, ...], snapshot: Callable[[], object], clock: Clock):
        self.clock = clock
        self.names = tuple(names)
        self.m = len(self.names)
        self.snapshot = snapshot
        self.lines: list[str] = []
        self.problems: list[str] = []
        self.vrpn: vrpn.VrpnServer | None = None
        self.vmc: vmc.VmcSender | None = None
        self.osc_period = 1.0 / settings.osc_hz
        if settings.vrpn_port is not None:
            self._open_vrpn(settings.host, settings.vrpn_port)
        if settings.osc_targets:
            targets, problems = vmc.parse_targets(settings.osc_targets)
            self.problems += problems
            if targets:
                self.vmc = vmc.VmcSender(targets)
                self.lines.append(f"VMC to {', '.join(t.label for t in targets)} at {settings.osc_hz:g} Hz")
        self.lines += self.problems
        self._queue: collections.deque[Frames] = collections.deque(maxlen=QUEUE_BATCHES)  # the reader's batches
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._woken = False
        self._lock = threading.Lock()  # the streams' state below: whichever thread serves them holds it
        # While a VRPN client takes every frame, and the pipeline does not come by, `feed` wakes the streams'
        # thread for every second frame (PAIR_S); VMC's ticks take the newest.
        self._eager = False
        self._handed_at = -np.inf  # when the pipeline's thread last came by (`hand_over`)
        self._unwoken = 0  # frames queued since `feed` last woke the thread (`feed`'s own)
        self._fed_t = -np.inf  # the newest queued frame's time (`feed`'s own)
        self._stop = False
        self._thread: threading.Thread | None = None
        # Below: the streams' own, under `_lock`.
        self._waiting: collections.deque[Frames] = collections.deque(maxlen=QUEUE_BATCHES)  # taken, not yet sent
        self._sent_t = -np.inf  # the newest frame the streams took
        self._next_osc, self._last_osc = clock.monotonic(), -np.inf  # VMC's tick grid, its last bundle
        self._next_tick = 0.0  # the VRPN server's and the status's half-second tick
        self._next_look = -np.inf  # when frames no stream sends are next taken (LOOK_S)
        self._held = (np.full((self.m, 3, 3), np.nan), np.full((self.m, 3), np.nan))
        self._newest: tuple | None = None  # (reader time, valid (m,), whether every sensor is) of the newest frame
        self._segments: tuple | None = None  # (reader time, positions, rotations, VMC's local quaternions or None)
        self._sample = (np.zeros((SAMPLE_FRAMES, self.m, 3, 3)), np.zeros((SAMPLE_FRAMES, self.m, 3)),
                        np.zeros((SAMPLE_FRAMES, self.m), dtype=bool))
        self._sampled, self._sample_t = 0, -np.inf
        self._fit = None
        self._rig: HumanoidRig | None = None
        self._packer: vrpn.ReportPacker | None = None  # the rig's VRPN messages, laid out once
        self._layout: vmc.BoneLayout | None = None  # the rig's VMC bones, laid out once
        self._bone_sensors = np.zeros(0, dtype=int)  # the rig's bones' sensors, in its `present` order
        self._rig_at = -np.inf
        self._rig_stale = False
        self._retry: tuple = (None, -np.inf)  # (a fit that gave no rig, when to try it again)
        self._rig_key: tuple = (None, None)  # whose fit the rig is: snapshot's pose_fit_id
        self._session = None  # the live session as the snapshot the rig was followed in showed it
        self._humanoid: tuple | None = None  # (the tree it was found on, when, the Humanoid)
        self.reason: str | None = "no fit yet"
        self._bundles: dict[tuple, vmc.Bundle] = {}
        self._t0 = clock.monotonic()
        self._status: dict = {}

    def _open_vrpn(self, host: str, port: int) -> None:
        if not 0 <= port <= 65535:
            self.problems.append(f"VRPN not started: {port} is not a port (1-65535); give --vrpn PORT")
            return
        try:
            self.vrpn = vrpn.VrpnServer(host, port, self.clock, sensors=len(BONES))
        except OSError as exc:
            why = ("another program (another VRPN server?) uses it" if exc.errno == errno.EADDRINUSE
                   else exc.strerror or str(exc))
            self.problems.append(f"VRPN not started: cannot listen on {host} port {port} (TCP and UDP): {why}; "
                                 "choose another with --vrpn PORT — the service runs without VRPN")
            return
        self.lines.append(f"VRPN tracker flockcal@{host}:{self.vrpn.port} (TCP and UDP; sensors 0-15: "
                          f"{', '.join(BONES)})")

    @property
    def active(self) -> bool:
        return self.vrpn is not None or self.vmc is not None

    # -- any thread ---------------------------------------------------------------------------------------
    def feed(self, frames: Frames) -> None:
        """A batch from the reader: queued. Only while the pipeline's thread has not come by for STAND_IN_S (it
        does the streams' work at its steps) is the streams' own thread woken, as it would: when a VRPN client
        waits for the frames and a second frame is here (or this one came over PAIR_S after the last). Never
        blocks."""
        n = len(frames)
        if not n:
            return
        self._queue.append(frames)
        self._unwoken += n
        gap, self._fed_t = frames.times[-1] - self._fed_t, frames.times[-1]
        if not self._eager or self._fed_t - self._handed_at < STAND_IN_S:
            return
        if self._unwoken >= 2 or gap > PAIR_S:
            self._unwoken = 0
            if not self._woken:
                self._woken = True
                try:
                    self._wake_w.send(b"\0")
                except (BlockingIOError, OSError):
                    pass

    def hand_over(self) -> float:
        """The streams' work for the frames queued since (the pipeline's thread, at each of its steps): sent in
        twos while a VRPN client takes them, with VMC's bundle when due. Returns when it wants to be called
        again with no new frames (a lone frame's STALL_S, VMC's next tick; inf: not before frames come).
        Never waits: while the streams' own thread holds their state, the next step takes the frames."""
        if self._stop:
            return np.inf
        now = self.clock.monotonic()
        self._handed_at = now
        if not self._lock.acquire(blocking=False):
            return now + PAIR_S
        try:
            return self._serve(now)
        except Exception:
            log.exception("outputs: a step failed; the streams go on with the next frames")
            return now + STALL_S
        finally:
            self._lock.release()

    def start(self) -> None:
        if not self.active:
            return
        self._status = self._make_status()
        self._thread = threading.Thread(target=self._run, name="flockcal-outputs", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop = True
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:  # the pipeline's thread may be in `hand_over`: it sends nothing from here on
            if self.vrpn is not None:
                self.vrpn.close()
            if self.vmc is not None:
                self.vmc.close()
        self._wake_r.close()
        self._wake_w.close()

    def status(self) -> dict:
        """Which outputs run, their clients and targets (/api/status `outputs`; refreshed twice a second)."""
        return self._status if self._thread is not None else self._make_status()

    # -- the thread ---------------------------------------------------------------------------------------
    def _run(self) -> None:
        """The sockets (VRPN's clients, the wake-ups), the half-second tick, and the streams' work while the
        pipeline's thread does not come by (STAND_IN_S)."""
        name_os_thread("fc-outputs")
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ, self._drain_wake)
        if self.vrpn is not None:
            self.vrpn.register(sel)
        due = self.clock.monotonic()  # when the streams want serving, while this thread stands in
        while not self._stop:
            now = self.clock.monotonic()
            handed = self._handed_at + STAND_IN_S  # until then the pipeline's thread serves the streams
            timeout = max(0.0, min(self._next_tick, due if now >= handed else handed) - now)
            events = sel.select(timeout)
            with self._lock:
                for key, mask in events:
                    try:
                        key.data(mask)
                    except Exception:  # one client's fault is not the stream's: log it, go on
                        log.exception("outputs: a socket event failed")
                now = self.clock.monotonic()
                try:
                    if now - self._handed_at >= STAND_IN_S:
                        due = self._serve(now)
                        if self._eager and self._newest is not None and now - self._newest[0] < 10 * STALL_S:
                            due = min(due, now + STALL_S)  # frames are coming: a lone one before a pause is not held long
                    if now >= self._next_tick:
                        if self.vrpn is not None:
                            self.vrpn.tick(now)
                        self._status = self._make_status()
                        self._next_tick = now + 0.5
                except Exception:
                    log.exception("outputs: a step failed; the streams go on with the next frames")
        sel.close()

    def _serve(self, now: float) -> float:
        """The streams' work at `now` (under `_lock`): the frames taken, sent while a VRPN client takes them (two
        at a time: PAIR_S), VMC's bundle when its tick is due. Returns when it next wants to run with no new
        frames."""
        self._eager = eager = self.vrpn is not None and self.vrpn.streaming
        while self._queue:
            self._waiting.append(self._queue.popleft())
        waiting = self._waiting
        send = False
        if eager and waiting:
            last = waiting[-1].times
            n = len(waiting[0]) if len(waiting) == 1 else 2
            before = last[-2] if len(last) > 1 else (waiting[-2].times[-1] if len(waiting) > 1 else self._sent_t)
            send = n >= 2 or last[-1] - before > PAIR_S or now - last[-1] >= STALL_S
        spacing = OSC_SPACING * self.osc_period
        osc_due = (self.vmc is not None and now >= self._next_osc and now - self._last_osc >= spacing
                   and (send or not eager or now >= self._next_osc + OSC_GRACE_S))
        followed = False
        if send or osc_due or (waiting and now >= self._next_look):
            followed = self._frames(list(waiting), osc_due)
            waiting.clear()
            self._next_look = now + LOOK_S
        if osc_due:
            self._send_vmc(now, self._next_osc, followed)
            self._last_osc = now
            # A fixed grid, so the rate holds: a late tick is caught up by the next hand-overs (OSC_SPACING
            # apart); held up OSC_BEHIND periods, the ticks missed are skipped, not sent in a burst.
            late = now - self._next_osc
            self._next_osc += self.osc_period * (1 if late < OSC_BEHIND * self.osc_period
                                                 else np.ceil(late / self.osc_period))
        due = np.inf
        if self.vmc is not None:
            due = max(self._next_osc + (OSC_GRACE_S if eager else 0.0), self._last_osc + spacing)
        if eager and self._waiting:
            due = min(due, self._waiting[-1].times[-1] + STALL_S)
        return due

    def _drain_wake(self, _mask) -> None:
        self._woken = False
        try:
            self._wake_r.recv(4096)  # one byte a wake-up, sent only while `_woken` was clear
        except (BlockingIOError, OSError):
            pass

    def _frames(self, batches: list[Frames], osc_due: bool = False) -> bool:
        """Frames taken from the reader's queue: held, sampled, and while a VRPN client takes them, sent; with a
        VMC bundle due now, its bones' local quaternions come out of the same `as_quat` call as VRPN's. Whether
        it followed the newest fit (it does whenever there were frames)."""
        streaming = self._eager  # whether a VRPN client takes every frame, as `_serve` read it
        if not streaming and batches and batches[-1].valid[-1].all():
            batches = [batches[-1][-1:]]  # VMC takes the newest frame: held poses need nothing before it
        if not batches:  # `feed` queues no empty batch
            return False
        last = batches[-1]
        # Every sensor valid in every frame, the usual case: the frames are their own held poses, and the rig
        # reads them batch by batch (a hand-over's first calls cost several times their warm cost: joining the
        # batches first cost as much as playing them through the rig).
        whole = all(np.logical_and.reduce(b.valid, axis=None) for b in batches)
        if whole:
            R = t = None
            self._held = (last.rotations[-1].copy(), last.positions[-1].copy())  # the reader may reuse its arrays
        else:
            f = Frames.concat(batches, self.m)
            R, t = held_poses(f.rotations, f.positions, f.valid, before=self._held)
            self._held = (R[-1], t[-1])
        newest = float(last.times[-1])
        self._newest, self._sent_t = (newest, last.valid[-1], whole), newest
        self._segments = None
        if newest - self._sample_t >= SAMPLE_S:
            k = self._sampled % SAMPLE_FRAMES
            self._sample[0][k], self._sample[1][k] = self._held
            self._sample[2][k] = np.isfinite(self._held[1]).all(axis=1)
            self._sampled += 1
            self._sample_t = newest
        self._follow_fit()
        rig = self._rig
        if rig is None or not streaming:
            return True
        if R is None:
            times = [t for b in batches for t in b.times.tolist()]  # a few frames: Python floats, no arrays
            x, at = np.empty((len(times), rig.width)), 0
            for b in batches:
                n = len(b.times)
                rig.inputs(b.rotations, b.positions, x[at:at + n])
                at += n
            pos, rot = rig.play(x, finite=True)  # every sensor valid: every pose is a reading
        else:
            pos, rot = rig.segments(R, t)
            times = f.times.tolist()
        n, k = rot.shape[:2]
        turns = rot.reshape(n * k, 3, 3)
        if osc_due:  # VMC's local rotations written after VRPN's: one `as_quat` for both
            turns = np.empty((n * k + k, 3, 3))
            turns[:n * k] = rot.reshape(n * k, 3, 3)
            self._layout.local(rot[-1], out=turns[n * k:])
        quats = as_quat(turns, scalar_first=False)
        self._segments = (newest, pos[-1], rot[-1], quats[n * k:] if osc_due else None)
        quats = quats[:n * k].reshape(n, k, 4)
        offset = self.clock.wall() - self.clock.monotonic()
        walls = [t + offset for t in times]  # the frames' wall times
        self.vrpn.send_reports(self._packer.frames(walls, pos, quats, finite=R is None))
        return True

    def _follow_fit(self) -> None:
        """The rig of the newest fit: the live session's own (not the last session's until it has one), or
        with no session live the last stopped session's final fit; rebuilt at most every RIG_REFRESH_S."""
        snap = self.snapshot()
        fit = getattr(snap, "pose_fit", None)
        key = getattr(snap, "pose_fit_id", None)  # (session id, fit number; None for its stored final fit)
        session = self._session = getattr(snap, "session", None)
        if session is not None and (key is None or key[0] != session.id):
            fit = None
        if fit is not self._fit:
            self._fit, self._rig_stale = fit, True
        elif not self._rig_stale:  # the usual case, at every hand-over that sends frames
            return
        now = self.clock.monotonic()
        # Another session's fit, a session's final fit or none at all: at once (what VMC's calibration
        # state says must be what its bones are); the same session's next live fit: at the refresh rate.
        urgent = fit is None or key is None or key[1] is None or key[0] != self._rig_key[0]
        if not self._rig_stale or (not urgent and now - self._rig_at < RIG_REFRESH_S):
            return
        if fit is not None and self._retry[0] is fit and now < self._retry[1]:
            return
        self._rig_at = now
        self._segments = None
        if fit is None:
            self._rig, self.reason, self._rig_stale, self._rig_key = None, "no fit yet", False, (None, None)
            return
        if not self._sampled:
            return  # no frame yet to find the humanoid from: the next frames try again
        self._rig_stale = False
        n = min(self._sampled, SAMPLE_FRAMES)
        order = (np.arange(n) + (self._sampled - n)) % SAMPLE_FRAMES
        sample = tuple(a[order] for a in self._sample)
        tree = tuple(np.asarray(fit.parent).tolist())
        try:
            if self._humanoid is None or self._humanoid[0] != tree or now - self._humanoid[1] >= HUMANOID_REFRESH_S:
                self._humanoid = (tree, now, humanoid_of(fit, sample))
            rig, reason = humanoid_rig(fit, self._humanoid[2], frames=sample), None
        except (FlockcalError, ValueError, np.linalg.LinAlgError) as exc:  # ArticulationError among them
            rig, reason = None, str(exc)
        if reason is not None and reason != self.reason:
            log.warning("VRPN and VMC send no bones: %s", reason)  # one line a change, not one a fit
        elif rig is not None and self._rig is None:
            log.info("VRPN and VMC stream the humanoid: %s", ", ".join(BONES[k] for k in rig.present))
        if rig is None and key is not None and key[1] is None:
            # A stopped session's final fit stays the same object (a live session's next fit is tried anyway):
            # found again from the frames come since (the first batch's sample alone finds no humanoid).
            self._retry, self._rig_stale, self._humanoid = (fit, now + RETRY_S), True, None
        if rig is not None:
            if self._rig is None or not np.array_equal(self._rig.present, rig.present):
                self._packer = vrpn.ReportPacker(rig.present)  # its layout hangs on the bones present only
            self._layout = vmc.BoneLayout(rig)
            self._bone_sensors = rig.sensor[rig.present]
        self._rig, self.reason, self._rig_key = rig, reason, key

    def _send_vmc(self, now: float, tick: float, followed: bool = False) -> None:
        """One bundle: the newest frame's bones once there is a rig, else /VMC/Ext/OK "not loaded"; its
        /VMC/Ext/T is the tick's time on the sender's grid (seconds since the streams started). `followed`:
        this hand-over's frames just followed the newest fit."""
        if not followed:
            self._follow_fit()
        rig, newest, session = self._rig, self._newest, self._session
        tracking = int(newest is not None and now - newest[0] <= TRACKING_S
                       and (rig is None or newest[2] or bool(np.logical_and.reduce(newest[1][self._bone_sensors]))))
        t = tick - self._t0
        numbers = None
        if rig is not None and newest is not None:
            if self._segments is not None and self._segments[0] == newest[0]:
                pos, rot, local = self._segments[1:]
            else:
                pos, rot = (a[0] for a in rig.segments(self._held[0][None], self._held[1][None]))
                self._segments, local = (newest[0], pos, rot, None), None
            numbers = (self._layout.numbers(pos, rot) if local is None
                       else self._layout.assemble(pos, local))
            # A sensor with no pose yet: the bones wait for one (a frame with every sensor valid has them all).
            if not newest[2] and not np.isfinite(np.add.reduce(numbers, axis=None)):
                numbers = None
        if numbers is None:
            state = vmc.CALIBRATING if session is not None else vmc.UNCALIBRATED
            self.vmc.send(self._bundle(()).fill((0, state, 0, tracking), t))
            return
        state = vmc.CALIBRATING if session is not None and not session.done else vmc.CALIBRATED
        self.vmc.send(self._bundle(self._layout.names).fill((1, state, 0, tracking), t, numbers))

    def _bundle(self, names: tuple) -> vmc.Bundle:
        if names not in self._bundles:
            self._bundles[names] = vmc.Bundle(names)
        return self._bundles[names]

    def _make_status(self) -> dict:
        rig = self._rig
        return {
            "vrpn": None if self.vrpn is None else self.vrpn.status(),
            "vmc": None if self.vmc is None else {**self.vmc.status(), "rate_hz": round(1 / self.osc_period, 3)},
            "humanoid": {"streaming": rig is not None, "reason": self.reason,
                         "bones": [] if rig is None else [BONES[k] for k in rig.present]},
            "problems": list(self.problems),
        }
