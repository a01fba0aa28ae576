"""Time to calibrate: simulated guests (different seeds and heights) do the kiosk routine from the moment
their session starts; how long until the service says `done`, how far the bones are then from the truth
and from the same guest's bones after 120 s. Targets (issue #30, the kiosk profile, the simulator's default
12 mm soft tissue): median ≤ 25 s, p90 ≤ 35 s, every guest done, bones at done within 5 mm of the bones
after 120 s; on rigid sensors (`--performer-option sta_mm=0`) median ≤ 20 s and bones within 5 mm of the
truth. `--profile stage` runs the operator's profile instead (solver/progress.py).

Two ways to run a guest, the same progress code either way (solver/progress.py):
- `--mode service` (the figures in README.md): a real `flockcal serve` process reads a fake tracker on a
  pty streaming the guest in real time; a session is started over REST and the websocket's `fit` messages
  are read until one says done (≈ 25 s of wall time per guest);
- `--mode pipeline` (quick, ≈ 5 s per guest): the service's own per-fit steps in session time, without
  driver, server or slip monitor: the segmented accumulator, `fit_calibration` and `ProgressTracker`, one
  refit every 1/30 s of data (the service's fit rate).

Bones: a bone between two ball joints is compared by length; a bone ending at a hinge (elbow, knee) by the
distance from its other joint centre to the hinge axis, since where along its axis a hinge's centre sits is
not in the data (the fit takes the minimum-norm point, design.md §2). Extra Performer options go through
`--performer-option KEY=VALUE` (repeatable; values are JSON, else text), e.g. soft-tissue artefact settings.

    python benchmarks/bench_calibrate_time.py --mode service            # 20 guests, ≈ 12 min
    python benchmarks/bench_calibrate_time.py --guests 5 --performer-option noise=null
    python benchmarks/bench_calibrate_time.py --performer-option sta_mm=0   # rigid sensors
    python benchmarks/bench_calibrate_time.py --real-knee       # the real knee capture, replayed as a take
"""

from __future__ import annotations

import argparse
import asyncio
import inspect
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flockcal.solver.progress import Profile, profile
from flockcal.simulator.performer import Performer

RATE = 144.0
TARGET_MEDIAN_S, TARGET_P90_S, TARGET_BONE_M = 25.0, 35.0, 0.005
REFERENCE_S = 120.0  # "the same guest's bones after 120 s"
GUEST_LEAD_S = 0.3  # see tests/server_helpers.py GuestSource


def performer_options(pairs: list[str]) -> dict:
    """--performer-option KEY=VALUE pairs as Performer keywords; exits naming the keyword it does not know."""
    accepted = set(inspect.signature(Performer).parameters) - {"self"}
    out = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or key not in accepted:
            sys.exit(f"--performer-option {pair!r}: give KEY=VALUE with KEY one of {', '.join(sorted(accepted))}")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out


def guests(n: int, seed0: int, heights: tuple[float, float]) -> list[tuple[int, float]]:
    rng = np.random.default_rng(seed0)
    return [(seed0 + k, round(float(h), 3)) for k, h in enumerate(rng.uniform(*heights, n))]


# ------------------------------------------------------------------------------------------- bones

def _points(fit: dict) -> dict:
    """{(body, frozenset(joint's two bodies)): (centre, hinge axis or None) in that body's sensor frame}."""
    out = {}
    for j in fit["joints"]:
        pair = frozenset((j["child"], j["parent"]))
        for body, point, axis in ((j["child"], j["c"], j.get("axis_child")), (j["parent"], j["l"], j.get("axis_parent"))):
            a = np.asarray(axis, dtype=float) if j.get("hinge") and axis is not None else None
            out[(body, pair)] = (np.asarray(point, dtype=float), a)
    return out


def _span(p1, a1, p2, a2) -> float | None:
    """Distance the data determine between two joint centres: point to point, or point to a hinge's axis."""
    if a1 is not None and a2 is not None:
        return None  # two hinge ends: no human bone has them
    if a1 is not None:
        (p1, a1), (p2, a2) = (p2, a2), (p1, a1)
    if a2 is None:
        return float(np.linalg.norm(p1 - p2))
    d = p1 - p2
    axis = a2 / np.linalg.norm(a2)
    return float(np.linalg.norm(d - axis * (d @ axis)))


def bone_errors(fit: dict, truth: dict) -> dict:
    """Worst |fitted − true| over the fit's bones, ball-ended and hinge-ended apart (m); inf for a bone
    between joints the simulated body does not have (a wrong tree)."""
    got, true = _points(fit), _points(truth)
    worst = {"ball": 0.0, "hinge": 0.0, "hinge_length": 0.0}
    for b in fit.get("bones") or []:
        keys = []
        for jn in (b["from_joint"], b["to_joint"]):
            if jn is None:
                continue
            keys.append((b["body"], frozenset((jn, fit["parent"][jn]))))
        if len(keys) != 2:
            continue
        if any(k not in true for k in keys):
            worst["ball"] = np.inf
            continue
        (p1, _), (p2, _) = got[keys[0]], got[keys[1]]
        (q1, h1), (q2, h2) = true[keys[0]], true[keys[1]]
        hinge = h1 is not None or h2 is not None
        a1, a2 = got[keys[0]][1], got[keys[1]][1]
        if hinge and (a1 is None) == (h1 is None) and (a2 is None) == (h2 is None):
            fitted, real = _span(p1, a1, p2, a2), _span(q1, h1, q2, h2)
            if fitted is not None and real is not None:
                worst["hinge"] = max(worst["hinge"], abs(fitted - real))
            worst["hinge_length"] = max(worst["hinge_length"], abs(float(np.linalg.norm(p1 - p2) - np.linalg.norm(q1 - q2))))
        elif hinge:
            worst["hinge"] = np.inf  # fitted as a ball where the body has a hinge, or the other way round
        else:
            worst["ball"] = max(worst["ball"], abs(float(np.linalg.norm(p1 - p2) - np.linalg.norm(q1 - q2))))
    return worst


# ------------------------------------------------------------------------------------------ guests

def reference_fit(perf: Performer, tolerance_m: float, seconds: float = REFERENCE_S) -> dict:
    """The guest's fit after `seconds` of the routine (the same per-fit code as the service, one fit)."""
    from flockcal.server.fitting import fit_calibration
    from flockcal.solver.segments import SegmentedAccumulator

    acc = SegmentedAccumulator(perf.n_sensors)
    for k in range(int(seconds)):
        times = np.arange(int(k * RATE), int((k + 1) * RATE)) / RATE
        acc.ingest(times, *perf.poses(times))
    return fit_calibration(acc, perf.names, tolerance=tolerance_m)[0]


def bones_moved(fit: dict, later: dict) -> float:
    """Worst |length at done − length after REFERENCE_S| over the later fit's bones (m); inf when the tree or
    the bones drawn differ."""
    a = {(b["body"], b["from_joint"], b["to_joint"]): b["length_m"] for b in fit.get("bones") or []}
    b = {(x["body"], x["from_joint"], x["to_joint"]): x["length_m"] for x in later.get("bones") or []}
    if fit.get("parent") != later.get("parent") or set(a) != set(b) or not b:
        return float("inf")
    return max(abs(a[k] - b[k]) for k in b)


def run_pipeline(perf: Performer, max_s: float, prof: Profile, fit_hz: float = 30.0) -> dict:
    from flockcal.server.fitting import fit_calibration
    from flockcal.solver.segments import SegmentedAccumulator
    from flockcal.solver.progress_tracker import ProgressTracker

    acc = SegmentedAccumulator(perf.n_sensors)
    tracker = ProgressTracker.for_profile(prof)
    frames = int(round(RATE / fit_hz))
    docs = []
    for k in range(int(max_s * fit_hz)):
        times = np.arange(k * frames, (k + 1) * frames) / RATE
        R, t, valid = perf.poses(times)
        acc.ingest(times, R, t, valid)
        fit, cal = fit_calibration(acc, perf.names, tolerance=prof.tolerance_m)
        doc = tracker.add_fit(cal, float(times[-1])).to_dict()  # the typed fit, as the service passes it
        docs.append((float(times[-1]), doc))
        if doc["done"]:
            return {"done_s": doc["done_at_s"], "fit": fit, "docs": docs}
    return {"done_s": None, "fit": None, "docs": docs}


def run_service(guest_list, options, max_s: float, prof: Profile, tolerance_m: float, target_m: float) -> list[dict]:
    import httpx

    # The service runner is a test helper (it needs httpx, a test-only extra): it lives in tests/.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from server_helpers import GuestSource, ServerProcess, free_port, wait_connected
    from flockcal.simulator.pty_tracker import PtyTracker

    first = Performer("human", "kiosk", seed=guest_list[0][0], rate_hz=RATE, height=guest_list[0][1], **options)
    tracker = PtyTracker(first, birds=first.n_sensors, baud=921600, rate_hz=RATE)
    stream = GuestSource(first, tracker.flock.clock)
    tracker.flock.source = stream
    tracker.start()
    out = []
    with tempfile.TemporaryDirectory() as data:
        port = free_port()
        args = ["--device", tracker.device, "--birds", str(first.n_sensors), "--names", ",".join(first.names),
                "--scale", "72", "--baud", "921600", "--fast-init", "--data-dir", data,
                "--tolerance-mm", f"{tolerance_m * 1000:g}"]
        if prof.name == "stage":
            args += ["--target-mm", f"{target_m * 1000:g}"]
        server = ServerProcess(args, port).start()
        try:
            wait_connected(server.url, timeout=60)
            for seed, height in guest_list:
                perf = Performer("human", "kiosk", seed=seed, rate_hz=RATE, height=height, **options)
                stream.begin(perf, lead_s=GUEST_LEAD_S)  # no frame of the last guest's body in this session
                time.sleep(GUEST_LEAD_S)
                sid = httpx.post(f"{server.url}/api/sessions", json={"performer": f"guest {seed}",
                                                                      "profile": prof.name}).json()["id"]
                docs = asyncio.run(_follow(server.url, sid, max_s))
                httpx.post(f"{server.url}/api/sessions/{sid}/stop", timeout=60)
                done = next(((t, d) for t, d in docs if d.get("done")), None)
                out.append({"seed": seed, "height": height, "perf": perf, "docs": docs, "profile": prof,
                            "done_s": done[1]["done_at_s"] if done else None, "fit": done[1]["result"] if done else None})
                _report(out[-1])
        finally:
            server.stop()
            tracker.stop()
    return out


async def _follow(url: str, sid: str, max_s: float) -> list:
    import websockets

    docs = []
    async with websockets.connect(url.replace("http://", "ws://") + "/ws/live", max_size=None) as ws:
        await ws.send(json.dumps({"type": "subscribe", "rate_hz": 1000, "content": ["fit"]}))
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if msg.get("type") != "fit" or (msg.get("session") or {}).get("id") != sid:
                continue
            t = msg["session"]["time_s"]
            docs.append((t, msg))
            if msg["done"] or t > max_s:
                return docs


# ------------------------------------------------------------------------------------------ report

def _drops(docs) -> list:
    """Moments the published progress went down: the joints whose share fell, each with the reason its
    entry states (slip, loss, tree; None: no reason given)."""
    out, prev, before = [], 0.0, {}
    for t, d in docs:
        now = {j["joint"]: j for j in d.get("joint_progress") or []}
        if d["progress"] < prev - 1e-9:
            fell = [(k, (j.get("undone") or {}).get("reason")) for k, j in now.items()
                    if k in before and j["progress"] < before[k]["progress"] - 1e-9]
            out.append((round(t, 2), fell))
        prev, before = d["progress"], now
    return out


def _last(docs) -> str:
    """The joints still missing one second before done: what the guest waited for."""
    if not docs:
        return ""
    t_end = docs[-1][0]
    before = [d for t, d in docs if t <= t_end - 1.0] or [docs[0][1]]
    return ", ".join(m["label"] for m in before[-1]["missing"][:4])


def _report(g: dict) -> None:
    g["bones"] = bone_errors(g["fit"], g["perf"].truth()) if g["fit"] else None
    g["moved"] = bones_moved(g["fit"], reference_fit(g["perf"], g["profile"].tolerance_m)) if g["fit"] else None
    g["drops"] = _drops(g["docs"])
    done = f"{g['done_s']:5.1f} s" if g["done_s"] is not None else "  not done"
    bones = (f"ball bones {1000 * g['bones']['ball']:4.1f} mm, hinge bones to axis {1000 * g['bones']['hinge']:4.1f} mm "
             f"(length {1000 * g['bones']['hinge_length']:4.1f} mm)") if g["bones"] else ""
    moved = f"bones vs {REFERENCE_S:g} s {1000 * g['moved']:4.1f} mm" if g["moved"] is not None else ""
    print(f"  seed {g['seed']:4d}  height {g['height']:.2f} m  done {done}  {moved}  {bones}  progress drops {len(g['drops'])}"
          f"  last: {_last(g['docs'])}", flush=True)
    for drop in g["drops"][:3]:
        print(f"      drop at {drop[0]} s: {drop[1][:4]}")


def real_knee(prof: Profile, fit_hz: float = 30.0) -> None:
    """The real knee trial (../shared/data/biobuddy_right_knee.c3d, 9.2 s at 100 Hz) replayed as a 15-sensor
    take (each technical cluster's rigid fit is a sensor, tests/real_captures.py) through the same per-fit
    steps: when the right knee counts under `prof`, and what the rest of the body (which hardly moves in
    a knee trial) is waiting for."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from real_captures import KNEE, cluster_take  # noqa: E402

    from flockcal.server.fitting import fit_calibration

    from flockcal.solver.segments import SegmentedAccumulator
    from flockcal.solver.progress_tracker import ProgressTracker

    take = cluster_take(KNEE)
    acc = SegmentedAccumulator(take.n_sensors)
    tracker = ProgressTracker.for_profile(prof)
    rate = 1.0 / float(np.median(np.diff(take.times)))
    step = max(1, int(round(rate / fit_hz)))
    knee_at, doc, knee = None, None, None
    for k in range(0, len(take.times), step):
        sl = slice(k, k + step)
        acc.ingest(take.times[sl], take.rotations[sl], take.positions[sl], take.valid[sl])
        cal = fit_calibration(acc, list(take.names), tolerance=prof.tolerance_m)[1]
        doc = tracker.add_fit(cal, float(take.times[sl][-1] - take.times[0])).to_dict()
        knee = next((j for j in doc["joint_progress"] if {j["joint"], j["parent"]} == {"r_thigh", "r_shank"}), None)
        if knee is not None and knee["done"] and knee_at is None:
            knee_at = float(take.times[sl][-1] - take.times[0])
    print(f"real knee trial ({len(take.times)} frames, {take.times[-1] - take.times[0]:.1f} s), profile {prof.name}: "
          f"the right knee " + (f"counts at {knee_at:.1f} s" if knee_at is not None else
                                f"does not count by the end ({knee['state'] if knee else 'not a joint of the tree'}: "
                                f"{knee['why'] if knee else ''})"))
    print(f"  at the end: {doc['joints_done']}/{doc['joints_needed']} joints, {doc['percent']} %, done {doc['done']}; "
          f"waiting for: " + "; ".join(f"{m['label']} ({m['state']})" for m in doc["missing"][:6]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", choices=("pipeline", "service"), default="pipeline")
    ap.add_argument("--guests", type=int, default=20)
    ap.add_argument("--seed", type=int, default=100, help="first guest's seed (guest k: seed + k)")
    ap.add_argument("--heights", default="1.5:1.95", metavar="LOW:HIGH", help="guests' heights, metres (uniform)")
    ap.add_argument("--max-s", type=float, default=60.0, help="give a guest up after this much session time")
    ap.add_argument("--profile", choices=("kiosk", "stage"), default="kiosk", help="how a session decides it is done")
    ap.add_argument("--tolerance-mm", type=float, default=5.0, help="the stage profile's (and the service's)")
    ap.add_argument("--target-mm", type=float, default=None, help="stage profile; default: --tolerance-mm / √2")
    ap.add_argument("--performer-option", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--real-knee", action="store_true",
                    help="replay ../shared/data/biobuddy_right_knee.c3d as a take instead of simulated guests")
    args = ap.parse_args()
    options = performer_options(args.performer_option)
    lo, hi = (float(x) for x in args.heights.split(":"))
    tol = args.tolerance_mm / 1000.0
    prof = profile(args.profile, tol, None if args.target_mm is None else args.target_mm / 1000.0)
    target = prof.target_m
    if args.real_knee:
        real_knee(prof)
        return
    guest_list = guests(args.guests, args.seed, (lo, hi))
    print(f"{args.guests} guests, kiosk routine, {RATE:g} Hz, 16 sensors, profile {prof.name} (tolerance "
          f"{prof.tolerance_m * 1000:g} mm), mode {args.mode}, performer options {options or 'none'}")
    start = time.perf_counter()
    if args.mode == "service":
        results = run_service(guest_list, options, args.max_s, prof, tol, target)
    else:
        results = []
        for seed, height in guest_list:
            perf = Performer("human", "kiosk", seed=seed, rate_hz=RATE, height=height, **options)
            g = {"seed": seed, "height": height, "perf": perf, "profile": prof, **run_pipeline(perf, args.max_s, prof)}
            _report(g)
            results.append(g)
    took = time.perf_counter() - start

    times = np.array([g["done_s"] if g["done_s"] is not None else np.inf for g in results])
    finished = np.isfinite(times)
    med, p90 = np.median(times), np.percentile(times, 90) if finished.all() else np.inf
    ball = np.array([g["bones"]["ball"] if g["bones"] else np.inf for g in results])
    hinge = np.array([g["bones"]["hinge"] if g["bones"] else np.inf for g in results])
    moved = np.array([g["moved"] if g["moved"] is not None else np.inf for g in results])
    drops = sum(len(g["drops"]) for g in results)
    print(f"done: {finished.sum()}/{len(results)} guests within {args.max_s:g} s")
    print(f"time to done: median {med:.1f} s ({med / TARGET_MEDIAN_S:.2f}× the {TARGET_MEDIAN_S:g} s target), "
          f"p90 {p90:.1f} s ({p90 / TARGET_P90_S:.2f}× the {TARGET_P90_S:g} s target), "
          f"range {times[finished].min() if finished.any() else np.inf:.1f}–{times.max():.1f} s")
    print(f"bones at done: ball-ended worst {1000 * ball.max():.1f} mm (median guest {1000 * np.median(ball):.1f} mm), "
          f"hinge-ended (to the axis) worst {1000 * hinge.max():.1f} mm (median {1000 * np.median(hinge):.1f} mm); "
          f"within {TARGET_BONE_M * 1000:g} mm: {int(((ball <= TARGET_BONE_M) & (hinge <= TARGET_BONE_M)).sum())}/{len(results)} guests")
    print(f"bones at done against the same guest's after {REFERENCE_S:g} s: worst {1000 * moved.max():.1f} mm, median "
          f"{1000 * np.median(moved):.1f} mm; within {TARGET_BONE_M * 1000:g} mm: {int((moved <= TARGET_BONE_M).sum())}/{len(results)}")
    unstated = sum(1 for g in results for _t, fell in g["drops"] if not fell or any(r is None for _j, r in fell))
    print(f"progress went down {drops} times in all, {unstated} of them with no stated reason ({took:.0f} s of wall time)")


if __name__ == "__main__":
    main()
