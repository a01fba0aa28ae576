"""The service's threads' work measured in process, where the load of a shared machine moves the figures far
less than it moves a whole service's (issue 33): CPU time of the thread doing it (`time.thread_time`).

- replay: 40 s of 16 birds at 144 Hz (the exercise bench_server.py's fake tracker plays) into a session's
  `LiveCalibration` as the pipeline thread drives it — reader hand-overs of `--chunk` frames, a refit of
  `fit_input` every 1/30 s of session time folded in with `add_fit` — split into the pipeline's side
  (`add_frames`: accumulator, slip loop, residuals; `add_fit`: progress) and the fit's (`solve_fit`).
  A digest of everything it returned (slip events, residual samples, progress) says whether two codes
  decide the same.
- reader: the tracker reader (`TrackerReader`, the service's 5 ms hand-over) on a pty fake tracker at
  921600 baud for `--reader-seconds`: its thread's CPU and wake-ups a second.
- service: the service's own `Pipeline` (its fit thread, frame log, SQLite store and snapshots) with a live
  session, fed the same performer as the tracker sends it (words decoded, and handed over with the frames
  where the code takes them) in real time, 5 ms hand-overs,
  for `--pipeline-seconds` after 5 s: each pipeline step's CPU (its p99 is the tail a snapshot, and so a
  client's latency, waits for) and every thread's share (fc-framelog: the frame log's writer).

    python benchmarks/bench_service_parts.py [--seconds 40] [--reader-seconds 15] [--chunk 1] [--pipeline-seconds 15]
    python benchmarks/bench_service_parts.py --ab main --rounds 3

`--ab REV` runs REV's code (exported as bench_server.py does) and this tree's in turn, each in a fresh
process, the order swapped every round, and prints each pair's ratio B/A. Asserts nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `flockcal serve` runs BLAS (set before numpy loads)

import numpy as np  # noqa: E402

RATE = 144.0
FIT_HZ = 30.0


def replay(seconds: float, chunk: int) -> dict:
    from flockcal.frames import Frames
    from flockcal.server.fitting import solve_fit
    from flockcal.simulator.performer import Performer
    from flockcal.solver.live import LiveCalibration
    from flockcal.solver.progress import profile

    perf = Performer("human", "exercise", seed=1, rate_hz=RATE)
    n = int(seconds * RATE)
    times = np.arange(n) / RATE
    R, t, v = perf.poses(times)
    live = LiveCalibration(perf.names, RATE, profile("stage", 0.005), detect_slips=True, residual_period_s=1 / 20)
    digest = hashlib.sha256()
    cpu = {"add_frames": 0.0, "add_fit": 0.0, "fit": 0.0}
    counts = {"events": 0, "fits": 0}

    def keep(update) -> None:
        counts["events"] += len(update.events)
        digest.update(repr([(type(e).__name__, e.time_s, getattr(e, "sensor", None)) for e in update.events]).encode())
        digest.update(repr([(r.time_s, r.rms_m.tobytes()) for r in update.residuals]).encode())
        if update.progress is not None:
            digest.update(repr(update.progress.to_dict()).encode())

    next_fit = 0.0
    for a in range(0, n, chunk):
        sl = slice(a, a + chunk)
        frames = Frames(5000.0 + times[sl], R[sl], t[sl], v[sl])
        c0 = time.thread_time()
        update = live.add_frames(frames)
        cpu["add_frames"] += time.thread_time() - c0
        keep(update)
        if live.time_s >= next_fit and live.fit_due:
            c0 = time.thread_time()
            job = live.fit_input()
            cal = solve_fit(job.acc, perf.names, None, None, None, 0.005)
            c1 = time.thread_time()
            update = live.add_fit(cal, job.time_s, job.epoch)
            cpu["add_fit"] += time.thread_time() - c1
            cpu["fit"] += c1 - c0
            counts["fits"] += 1
            keep(update)
            next_fit += 1 / FIT_HZ
    keep(live.finish())
    pct = {k: 100.0 * s / seconds for k, s in cpu.items()}
    return {"pipeline": pct["add_frames"] + pct["add_fit"], "progress": pct["add_fit"], "fit": pct["fit"],
            "fits": counts["fits"], "events": counts["events"], "digest": digest.hexdigest()[:16]}


def _thread_stats(name: str) -> tuple[float, int]:
    for tid in os.listdir("/proc/self/task"):
        try:
            if Path(f"/proc/self/task/{tid}/comm").read_text().strip() != name:
                continue
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
            status = Path(f"/proc/self/task/{tid}/status").read_text().splitlines()
        except OSError:
            continue
        wakes = next(int(line.split()[1]) for line in status if line.startswith("voluntary_ctxt_switches"))
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), wakes
    raise SystemExit(f"bench_service_parts: no thread named {name}")


def reader(seconds: float) -> dict:
    from flockcal.drivers.link import Timing
    from flockcal.drivers.reader import TrackerConfig, TrackerReader
    from flockcal.simulator.performer import Performer
    from flockcal.simulator.pty_tracker import PtyTracker

    pty = PtyTracker(Performer("human", "exercise", seed=1, rate_hz=RATE), birds=16, baud=921600, rate_hz=RATE).start()
    got = [0]
    rd = TrackerReader(TrackerConfig(urls=[pty.device], birds=16, rate_hz=RATE, baud=921600, scale_inches=72,
                                     timing=Timing.fast(), batch_interval=0.005),
                       on_frames=lambda f: got.__setitem__(0, got[0] + len(f)))
    try:
        rd.start(wait=30)
        time.sleep(2.0)  # past the set-up and the assembler's anchoring
        c0, w0, n0, t0 = *_thread_stats("fc-tracker"), got[0], time.monotonic()
        time.sleep(seconds)
        c1, w1, n1, t1 = *_thread_stats("fc-tracker"), got[0], time.monotonic()
    finally:
        rd.stop()
        pty.stop()
    span = t1 - t0
    return {"reader": 100.0 * (c1 - c0) / span, "wakeups": (w1 - w0) / span, "frames_hz": (n1 - n0) / span}


def service(seconds: float, warm: float = 5.0) -> dict:
    import flockcal.server.pipeline as pipeline
    import flockcal.server.snapshot as snapshot
    from flockcal.drivers.records import decode_records, encode_records
    from flockcal.frames import Frames
    from flockcal.server.framelog import FrameLog
    from flockcal.server.live_session import LiveSession
    from flockcal.server.store import Store
    from flockcal.simulator.performer import Performer
    from flockcal.solver.progress import profile

    perf = Performer("human", "exercise", seed=1, rate_hz=RATE)
    n = int((seconds + warm + 2) * RATE)
    t = np.arange(n) / RATE
    R, p, _ = perf.poses(t)
    m = R.shape[1]
    raw = np.frombuffer(encode_records("position_matrix", R.reshape(-1, 3, 3), p.reshape(-1, 3), scale_inches=72),
                        np.uint8)
    R, p, _ = decode_records("position_matrix", raw.reshape(n * m, -1), scale_inches=72, group=False)
    R, p, valid = R.reshape(n, m, 3, 3), p.reshape(n, m, 3), np.ones((n, m), bool)
    try:  # the reader hands over the words it decoded (Frames.words) since issue 49; the frame log stores them
        from flockcal.drivers.records import FORMATS, decode_block_words
        from flockcal.frames import TrackerWords

        W = decode_block_words("position_matrix", raw.reshape(n * m, -1), scale_inches=72)[0].reshape(n, m, -1)

        def words(sl):
            return (TrackerWords(W[sl], FORMATS["position_matrix"].command, 72),)
    except ImportError:
        def words(sl):
            return ()
    names = tuple(perf.names)
    if hasattr(snapshot, "SourceStatus"):  # typed since issue 49
        from flockcal.drivers.tracker_status import TrackerStatus
        from flockcal.server.limits import DiskStatus

        def status():
            return snapshot.SourceStatus(TrackerStatus(connected=True, urls=["pty"]), "pty", False,
                                         DiskStatus(False, None, 0))
    else:
        def status():
            return {"connected": True}
    folder = Path(tempfile.mkdtemp(prefix="bench-service-parts-"))
    store = Store(folder / "flockcal.sqlite3")
    pipe = pipeline.Pipeline(names, store, status, publish_hz=200.0)  # the service's publish_hz
    ends: list[float] = []  # the pipeline thread's CPU at the end of each step (each ends with a publish)
    publish = pipe._publish

    def timed_publish():
        publish()
        ends.append(time.thread_time())

    pipe._publish = timed_publish
    pipe.start()
    try:
        store.insert_session({"id": "s", "performer": "p", "state": "live", "root": None, "hierarchy": None,
                              "names": list(names), "device": "pty", "rate_hz": RATE, "created_at": time.time(),
                              "frames": 0, "recording": "s.frames", "profile": "stage"})
        log = FrameLog(folder / "s.frames", list(names), RATE)
        prof = profile("stage", 0.005, 0.005 / 2 ** 0.5)
        try:
            live = LiveSession("s", "p", names, None, None, log, prof, started_wall=time.time(),
                               started_mono=time.monotonic())
        except TypeError:  # before the service's clock
            live = LiveSession("s", "p", names, None, None, log, prof)
        pipe.begin_session(live)
        t0, k, mark = time.monotonic(), 0, None
        while (now := time.monotonic() - t0) < warm + seconds:
            if mark is None and now >= warm:
                mark = (time.monotonic(), _threads_cpu(), len(ends))
            k1 = min(n, int(now * RATE) + 1)
            if k1 > k:  # what the reader hands over every 5 ms
                pipe.feed(Frames(1000.0 + t[k:k1], R[k:k1], p[k:k1], valid[k:k1], *words(slice(k, k1))))
                k = k1
            time.sleep(0.005)
        end = (time.monotonic(), _threads_cpu(), len(ends))
    finally:
        pipe.stop()
        shutil.rmtree(folder, ignore_errors=True)
    span = end[0] - mark[0]
    step = np.diff(ends[mark[2]:end[2]]) * 1000
    share = {k: 100.0 * (v - mark[1].get(k, 0.0)) / span for k, v in end[1].items()}
    return {"steps_hz": len(step) / span, "step_p50": float(np.percentile(step, 50)),
            "step_p99": float(np.percentile(step, 99)), "service_pipeline": share.get("fc-pipeline", 0.0),
            "service_framelog": share.get("fc-framelog", 0.0), "service_fit": share.get("fc-fit", 0.0)}


def _threads_cpu() -> dict[str, float]:
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            name = Path(f"/proc/self/task/{tid}/comm").read_text().strip()
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def run_side(pythonpath: str | None, args) -> dict:
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, __file__, "--one", "--seconds", str(args.seconds), "--reader-seconds",
           str(args.reader_seconds), "--chunk", str(args.chunk), "--pipeline-seconds", str(args.pipeline_seconds)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        raise SystemExit(f"bench_service_parts: a side failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def show(label: str, r: dict) -> str:
    return (f"{label}pipeline side {r['pipeline']:5.2f} % (progress {r['progress']:4.2f}), fit {r['fit']:5.2f} % "
            f"({r['fits']} fits), {r['events']} slip events, digest {r['digest']}; reader {r['reader']:4.2f} %, "
            f"{r['wakeups']:.0f} wake-ups/s, {r['frames_hz']:.1f} frames/s; service: step p50 {r['step_p50']:.2f} / p99 "
            f"{r['step_p99']:.1f} ms ({r['steps_hz']:.0f}/s), pipeline {r['service_pipeline']:.1f} %, frame log "
            f"{r['service_framelog']:.1f} %, fit {r['service_fit']:.1f} %; load {r['load']:.1f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="length of the replay")
    ap.add_argument("--reader-seconds", type=float, default=15.0, help="window of the reader's measurement (0: none)")
    ap.add_argument("--chunk", type=int, default=1, help="frames per reader hand-over in the replay")
    ap.add_argument("--pipeline-seconds", type=float, default=15.0,
                    help="window of the service pipeline's measurement (0: none)")
    ap.add_argument("--ab", metavar="REV", help="A/B mode: git revision REV's code against this tree's, in turn")
    ap.add_argument("--rounds", type=int, default=3, help="A/B mode: runs of each side (default 3)")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # one side, as JSON (A/B's child)
    args = ap.parse_args(argv)
    if args.one or not args.ab:
        r = replay(args.seconds, args.chunk)
        r.update(reader(args.reader_seconds) if args.reader_seconds > 0 else
                 {"reader": float("nan"), "wakeups": float("nan"), "frames_hz": float("nan")})
        r.update(service(args.pipeline_seconds) if args.pipeline_seconds > 0 else
                 dict.fromkeys(("steps_hz", "step_p50", "step_p99", "service_pipeline", "service_framelog",
                                "service_fit"), float("nan")))
        r["load"] = os.getloadavg()[0]
        print(json.dumps(r) if args.one else show("", r))
        return 0

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_server import ab_order, check_imports, export_revision, ratio_line, round_ratios, tree_site  # noqa: E402

    tmp = tempfile.mkdtemp(prefix="flockcal-ab-")
    try:
        sides = {"A": export_revision(args.ab, os.path.join(tmp, "a")), "B": tree_site(os.path.join(tmp, "b"))}
        for site in sides.values():  # each side's code, not the editable install's (bench_server.py)
            check_imports(site, tmp)
        print(f"A/B: A = {args.ab}, B = this tree; replay {args.seconds:g} s in {args.chunk}-frame hand-overs, "
              f"reader {args.reader_seconds:g} s, {args.rounds} rounds", flush=True)
        runs = []
        for k, side in ab_order(args.rounds):
            r = run_side(sides[side], args)
            runs.append((side, r))
            print(show(f"  round {k + 1} {side}: ", r), flush=True)
        for key in ("pipeline", "progress", "fit", "reader", "wakeups", "step_p99", "service_pipeline"):
            print("  " + ratio_line(f"{key:9s}", round_ratios(runs, key)))
        same = len({r["digest"] for _, r in runs}) == 1
        print(f"  the same slip events, residuals and progress on both sides: {'yes' if same else 'NO'}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
