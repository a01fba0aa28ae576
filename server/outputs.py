"""The live humanoid streams, VRPN (server/vrpn.py) and VMC (server/vmc.py): each frame's reports and VMC's
due bundle go out at the reader's hand-over, on sockets that never block; a thread of their own ("fc-outputs")
serves the VRPN clients' sockets and builds each new fit's rig (docs/server.md).
"""

from __future__ import annotations

import collections
import errno
import logging
import selectors
import socket
import threading
import time
from typing import Callable, NamedTuple

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.frames import Frames
from flockcal.server import vmc, vrpn
from flockcal.server.pose import quaternions
from flockcal.solver.humanoid import BONES, Humanoid
from flockcal.solver.humanoid_pose import HumanoidRig, humanoid_rig
from flockcal.solver.reconstruct import held_poses
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

RIG_REFRESH_S = 0.2  # a new fit reaches the streams' rig at most this often (fits come 30 times a second)
HUMANOID_REFRESH_S = 5.0  # the humanoid is found again this often, and whenever the tree changes
RETRY_S = 1.0  # a fit that gave no rig (too few frames yet to find the humanoid from) is tried again this often
SAMPLE_S, SAMPLE_FRAMES = 0.1, 600  # the frames the humanoid is found from: one every 0.1 s, the last minute
TRACKING_S = 0.25  # newer frames than this, every bone's sensor valid: VMC's tracking status is OK
QUIET_S = 0.05  # no batch from the reader for this long: the thread sends VMC's bundles on its own grid
QUEUE_BATCHES = 256  # batches waiting for the thread at most (the oldest go first: live streams want the newest)


def humanoid_of(fit, sample: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Humanoid:
    """Which body is which humanoid bone: the one place the streams ask. The fit the service published
    carries it (found by the fit thread from the session's sample); a fit without one that can pose a rig
    (read back from a stored §5 result) has it found here from a sample of the live frames."""
    hum = getattr(fit, "humanoid", None)
    if hum is not None and hum.posable:
        return hum
    from flockcal.solver.humanoid import find_humanoid

    return find_humanoid(fit, *sample)


class Live(NamedTuple):
    """What the streams send from, swapped whole when a new fit's rig is built."""

    rig: HumanoidRig | None
    packer: vrpn.ReportPacker | None  # the rig's VRPN messages, laid out once
    layout: vmc.BoneLayout | None  # the rig's VMC bones, laid out once
    session: object  # the live session as the snapshot the rig was followed in showed it


class Outputs:
    """VRPN and VMC out, as `settings` ask (`vrpn_port`, `osc_targets`, `osc_hz`). Built before the service
    serves: a port in use or a receiver that cannot be resolved is one line in `lines` (what `serve` prints)
    and the service runs without that output. `start` / `stop` run the thread; once it runs, `feed` (the
    reader's thread) sends what each batch owes the streams, under `_lock`, which the thread takes for its
    socket events (a thread woken per frame cost as much again as the work, on a machine whose caches other
    work keeps)."""

    def __init__(self, settings, names: tuple[str, ...], snapshot: Callable[[], object]):
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
        self._queue: collections.deque[Frames] = collections.deque(maxlen=QUEUE_BATCHES)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._woken = False
        self._stop = False
        self._thread: threading.Thread | None = None
        # Below: the streams' state, stepped under the lock by the reader's hand-over and by the thread.
        self._lock = threading.Lock()
        self._last_feed = -np.inf
        self._feed_gap = np.inf  # the reader's hand-overs' interval, smoothed
        self._next_osc = 0.0  # VMC's next tick on its fixed grid
        self._held = (np.full((self.m, 3, 3), np.nan), np.full((self.m, 3), np.nan))
        self._newest: tuple | None = None  # (reader time, valid (m,)) of the newest frame
        self._segments: tuple | None = None  # (reader time, rig, positions, rotations) worked out for it
        self._sample = (np.zeros((SAMPLE_FRAMES, self.m, 3, 3)), np.zeros((SAMPLE_FRAMES, self.m, 3)),
                        np.zeros((SAMPLE_FRAMES, self.m), dtype=bool))
        self._sampled, self._sample_t = 0, -np.inf
        self._fit = None
        self._fit_key = None  # the snapshot's pose_fit_id of `_fit`
        # The rig of the newest fit, its VRPN messages and VMC bones laid out once, and the live session as
        # the snapshot it was followed in showed it: built by the thread, published as one tuple.
        self._live = Live(None, None, None, None)
        self._rig_at = -np.inf
        self._rig_stale = False
        self._retry: tuple = (None, -np.inf)  # (a fit that gave no rig, when to try it again)
        self._rig_key: tuple = (None, None)  # whose fit the rig is: snapshot's pose_fit_id
        self._session = None  # the live session as the newest snapshot shows it
        self._humanoid: tuple | None = None  # (the tree it was found on, when, the Humanoid): the thread's
        self.reason: str | None = "no fit yet"
        self._bundles: dict[tuple, vmc.Bundle] = {}
        self._t0 = time.monotonic()
        self._status: dict = {}

    def _open_vrpn(self, host: str, port: int) -> None:
        if not 0 <= port <= 65535:
            self.problems.append(f"VRPN not started: {port} is not a port (1-65535); give --vrpn PORT")
            return
        try:
            self.vrpn = vrpn.VrpnServer(host, port, sensors=len(BONES))
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
        """A batch from the reader. Once the streams run: every frame's VRPN reports while a client takes
        them, VMC's bundle when its tick is due, the thread woken when a new fit waits for its rig. Sends
        never wait (non-blocking sockets; a VRPN client that stops reading is dropped); a fault is logged,
        never the reader's."""
        self._queue.append(frames)
        if self._thread is None or self._stop:
            return
        now = time.monotonic()
        gap = now - self._last_feed
        self._feed_gap = gap if gap > 1 else 0.8 * self._feed_gap + 0.2 * gap
        self._last_feed = now
        try:
            with self._lock:
                self._step(now, self._reader_ticks(now))
        except Exception:
            log.exception("outputs: a step failed; the streams go on with the next frames")

    def start(self) -> None:
        if not self.active:
            return
        self._status = self._make_status()
        self._next_osc = time.monotonic()
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
        if self.vrpn is not None:
            self.vrpn.close()
        if self.vmc is not None:
            self.vmc.close()
        self._wake_r.close()
        self._wake_w.close()

    def status(self) -> dict:
        """Which outputs run, their clients and targets (/api/status `outputs`; refreshed twice a second)."""
        return self._status if self._thread is not None else self._make_status()

    def _reader_ticks(self, now: float) -> bool:
        """Whether VMC's bundles go out at the reader's hand-overs: while they come at least twice a tick
        (each bundle then at most half a tick late on its grid); else, and when the tracker goes quiet, the
        thread keeps the grid (a 60 Hz tracker's frames would land either side of a 60 Hz tick)."""
        return now - self._last_feed <= QUIET_S and self._feed_gap <= self.osc_period / 2

    # -- under the lock -----------------------------------------------------------------------------------
    def _step(self, now: float, osc: bool) -> None:
        """The queued frames when they are owed (every frame to a VRPN client; the newest to a due VMC tick),
        VMC's bundle when due (`osc`: this caller keeps VMC's grid), and a poke to the thread when a new fit
        waits for its rig."""
        streaming = self.vrpn is not None and self.vrpn.streaming
        osc_due = osc and self.vmc is not None and now >= self._next_osc
        if self._queue and (streaming or osc_due):
            self._frames(streaming)
        if osc_due:
            self._send_vmc(now, self._next_osc)
            # A fixed grid, so the rate holds; a stream held up skips the ticks it missed rather than
            # sending them in a burst (each would carry the same newest pose).
            self._next_osc += self.osc_period * max(1, np.ceil((now - self._next_osc) / self.osc_period))
        if self._rig_due(now) and not self._woken:
            self._woken = True
            try:
                self._wake_w.send(b"\0")
            except (BlockingIOError, OSError):
                pass

    # -- the thread ---------------------------------------------------------------------------------------
    def _run(self) -> None:
        name_os_thread("fc-outputs")
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ, self._drain_wake)
        if self.vrpn is not None:
            self.vrpn.register(sel)
        next_tick = 0.0
        while not self._stop:
            now = time.monotonic()
            # While the reader's hand-overs keep VMC's grid, the thread only watches for them to slow down or
            # stop; then it keeps the grid itself.
            wake = next_tick
            if self.vmc is not None:
                wake = min(wake, self._last_feed + QUIET_S if self._reader_ticks(now) else self._next_osc)
            events = sel.select(max(0.0, wake - now))
            now = time.monotonic()
            try:
                with self._lock:
                    for key, mask in events:
                        try:
                            key.data(mask)
                        except Exception:  # one client's fault is not the stream's: log it, go on
                            log.exception("outputs: a socket event failed")
                    if self.vmc is not None and not self._reader_ticks(now):
                        self._step(now, True)
                    if now >= next_tick:
                        if self._queue:  # frames no stream asked for yet: the held poses and the sample
                            self._frames(self.vrpn is not None and self.vrpn.streaming)
                        if self.vrpn is not None:
                            self.vrpn.tick(now)
                        self._status = self._make_status()
                        next_tick = now + 0.5
                    due = self._rig_due(now)
                if due:
                    self._follow_fit(now)
            except Exception:
                log.exception("outputs: a step failed; the streams go on with the next frames")
        sel.close()

    def _drain_wake(self, _mask) -> None:
        self._woken = False
        try:
            self._wake_r.recv(4096)  # one byte a poke, sent only while `_woken` was clear
        except (BlockingIOError, OSError):
            pass

    def _frames(self, streaming: bool) -> None:
        batches = []
        while self._queue:
            batches.append(self._queue.popleft())
        if not streaming and batches and len(batches[-1]) and batches[-1].valid[-1].all():
            batches = [batches[-1][-1:]]  # VMC takes the newest frame: held poses need nothing before it
        f = Frames.concat(batches, self.m)
        if not len(f):
            return
        R, t = held_poses(f.rotations, f.positions, f.valid, before=self._held)
        self._held = (R[-1], t[-1])
        self._newest = (float(f.times[-1]), f.valid[-1])
        if f.times[-1] - self._sample_t >= SAMPLE_S:
            k = self._sampled % SAMPLE_FRAMES
            self._sample[0][k], self._sample[1][k] = R[-1], t[-1]
            self._sample[2][k] = np.isfinite(t[-1]).all(axis=1)
            self._sampled += 1
            self._sample_t = f.times[-1]
        live = self._live
        if live.rig is None or not streaming:
            return
        pos, rot = live.rig.segments(R, t)
        self._segments = (self._newest[0], live.rig, pos[-1], rot[-1])
        n, k = pos.shape[:2]
        quats = quaternions(rot.reshape(-1, 3, 3)).reshape(n, k, 4)
        wall = f.times + (time.time() - time.monotonic())
        self.vrpn.send_reports(live.packer.frames(wall, pos, quats))

    def _rig_due(self, now: float) -> bool:
        """Whether the newest fit must reach the rig now: the live session's own fit (not the last session's
        until it has one), or with no session live the last stopped session's final fit. Another session's
        fit, a session's final fit or none at all: at once (what VMC's calibration state says must be what
        its bones are); the same session's next live fit: every RIG_REFRESH_S at most. Cheap: every batch."""
        snap = self.snapshot()
        fit = getattr(snap, "pose_fit", None)
        key = getattr(snap, "pose_fit_id", None)  # (session id, fit number; None for its stored final fit)
        session = self._session = getattr(snap, "session", None)
        if session is not None and (key is None or key[0] != session.id):
            fit = None
        if fit is not self._fit:
            self._fit, self._fit_key, self._rig_stale = fit, key, True
        if not self._rig_stale or (self._retry[0] is fit and fit is not None and now < self._retry[1]):
            return False
        urgent = fit is None or key is None or key[1] is None or key[0] != self._rig_key[0]
        return (urgent or now - self._rig_at >= RIG_REFRESH_S) and (fit is None or self._sampled > 0)

    # -- the thread ---------------------------------------------------------------------------------------
    def _follow_fit(self, now: float) -> None:
        """The rig of the fit `_rig_due` found waiting, built off the lock (the humanoid found again when
        the tree changes and every HUMANOID_REFRESH_S) and published with the session it came with."""
        with self._lock:
            if not self._rig_due(now):
                return
            fit, key, session = self._fit, self._fit_key, self._session
            self._rig_at, self._rig_stale = now, False
            if fit is None:
                self._live, self.reason, self._rig_key = Live(None, None, None, session), "no fit yet", (None, None)
                return
            n = min(self._sampled, SAMPLE_FRAMES)
            order = (np.arange(n) + (self._sampled - n)) % SAMPLE_FRAMES
            sample = tuple(a[order] for a in self._sample)
        tree = tuple(np.asarray(fit.parent).tolist())
        try:
            found = self._humanoid
            if (found is None or found[0] != tree
                    or now - found[1] >= (HUMANOID_REFRESH_S if found[2].human else RETRY_S)):
                self._humanoid = (tree, now, humanoid_of(fit, sample))
            rig, reason = humanoid_rig(fit, self._humanoid[2], frames=sample), None
        except (FlockcalError, ValueError, np.linalg.LinAlgError) as exc:  # ArticulationError among them
            rig, reason = None, str(exc)
        if reason is not None and reason != self.reason:
            log.warning("VRPN and VMC send no bones: %s", reason)  # one line a change, not one a fit
        elif rig is not None and self._live.rig is None:
            log.info("VRPN and VMC stream the humanoid: %s", ", ".join(BONES[k] for k in rig.present))
        old = self._live
        if rig is None:
            live = Live(None, None, None, session)
        else:  # the messages' layout hangs on which bones are present only: kept while they stay
            same = old.rig is not None and np.array_equal(old.rig.present, rig.present)
            live = Live(rig, old.packer if same else vrpn.ReportPacker(rig.present), vmc.BoneLayout(rig), session)
        with self._lock:
            self._live, self.reason, self._rig_key = live, reason, key
            if rig is None:  # a stored fit stays the same object: without this it would never be tried again
                self._retry, self._rig_stale = (fit, now + RETRY_S), self._rig_stale or fit is self._fit

    def _send_vmc(self, now: float, tick: float) -> None:
        """One bundle: the newest frame's bones once there is a rig, else /VMC/Ext/OK "not loaded"; its
        /VMC/Ext/T is the tick's time on the sender's grid (seconds since the streams started)."""
        live, newest = self._live, self._newest
        rig = live.rig
        # The calibration state of the fit the bones are from (the thread may not have built the newest yet).
        session = live.session if rig is not None else self._session
        tracking = int(newest is not None and now - newest[0] <= TRACKING_S
                       and (rig is None or bool(newest[1][rig.sensor[rig.present]].all())))
        t = tick - self._t0
        numbers = None
        if rig is not None and newest is not None:
            seg = self._segments
            if seg is not None and seg[0] == newest[0] and seg[1] is rig:
                pos, rot = seg[2], seg[3]
            else:
                pos, rot = (a[0] for a in rig.segments(self._held[0][None], self._held[1][None]))
                self._segments = (newest[0], rig, pos, rot)
            numbers = live.layout.numbers(pos, rot)
            if not np.isfinite(numbers).all():  # a sensor with no pose yet: the bones wait for one
                numbers = None
        if numbers is None:
            state = vmc.CALIBRATING if session is not None else vmc.UNCALIBRATED
            self.vmc.send(self._bundle(()).fill((0, state, 0, tracking), t))
            return
        state = vmc.CALIBRATING if session is not None and not session.done else vmc.CALIBRATED
        self.vmc.send(self._bundle(live.layout.names).fill((1, state, 0, tracking), t, numbers))

    def _bundle(self, names: tuple) -> vmc.Bundle:
        if names not in self._bundles:
            self._bundles[names] = vmc.Bundle(names)
        return self._bundles[names]

    def _make_status(self) -> dict:
        rig = self._live.rig
        return {
            "vrpn": None if self.vrpn is None else self.vrpn.status(),
            "vmc": None if self.vmc is None else {**self.vmc.status(), "rate_hz": round(1 / self.osc_period, 3)},
            "humanoid": {"streaming": rig is not None, "reason": self.reason,
                         "bones": [] if rig is None else [BONES[k] for k in rig.present]},
            "problems": list(self.problems),
        }
