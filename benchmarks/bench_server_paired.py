"""The paired modes of bench_server.py (`--streams-paired`, `--ab-paired REV`): two services at the same time,
each with its fake tracker in a process of its own, both processes' CPU read over the same windows, so what
loads a shared machine loads both sides of each window's B − A. Run through bench_server.py.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import tempfile
import time

import httpx
import numpy as np

from bench_server import RATE, Service, code_site, cpu_seconds, thread_cpu, tree_site


def _paired_side(site: str, streams: bool, conn) -> None:
    """One side of a paired run, in a process of its own with its fake tracker: serve until told to stop."""
    try:
        with Service(site, streams=streams) as svc:
            if streams:  # the streams' cost is what they cost sending bones: the session's fit must be a humanoid
                wait_streaming(svc.proc.url)
            conn.send((svc.proc.proc.pid, svc.proc.url))
            conn.recv()
            conn.send(svc.vmc.received if streams else None)
    except BaseException as exc:
        conn.send(exc)
        raise


def wait_streaming(url: str, timeout: float = 120.0) -> None:
    """Until the service's streams send the humanoid's bones to a connected VRPN client: a live session's first
    fits (the first 10-20 s of the routine) are not human-shaped yet, and bones cost what sending none does not."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        out = httpx.get(url + "/api/status").json()["outputs"]
        if out["humanoid"]["streaming"] and any(c["state"] == "connected" for c in out["vrpn"]["clients"]):
            return
        time.sleep(0.5)
    raise RuntimeError(f"the streams sent no bones within {timeout:g} s: {out['humanoid']}")


def _paired_reading(pid: int, url: str) -> tuple:
    return cpu_seconds(pid), thread_cpu(pid), httpx.get(url + "/api/status").json()["fits"], time.monotonic()


def streams_paired(rounds: int, windows: int, seconds: float, rev: str | None = None) -> int:
    """The service without (A) and with (B) the streams at the same time; each window's B − A in points."""
    tmp = tempfile.mkdtemp(prefix="flockcal-streams-paired-")
    try:
        site, code = code_site(rev, tmp)
        print(f"streams paired A/B of {code}: A (no streams) and B (--vrpn and --osc, vrpn_print_devices and a VMC "
              f"receiver attached) at the same time, each with its fake tracker in a process of its own; 16 birds "
              f"at {RATE:g} Hz, no websocket client; {rounds} rounds of {windows} windows of {seconds:g} s", flush=True)
        return paired({"A": (site, False), "B": (site, True)}, rounds, windows, seconds, "streams add", "at most +3")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def ab_paired(rev: str, rounds: int, windows: int, seconds: float) -> int:
    """The service of revision REV (A) and of this tree (B) at the same time; each window's B − A in points."""
    tmp = tempfile.mkdtemp(prefix="flockcal-ab-paired-")
    try:
        site_a, code = code_site(rev, os.path.join(tmp, "a"))
        site_b = tree_site(os.path.join(tmp, "b"))
        print(f"paired A/B: A = {code}, B = this tree, at the same time, each with its fake tracker in a process of "
              f"its own; 16 birds at {RATE:g} Hz, no websocket client; {rounds} rounds of {windows} windows of "
              f"{seconds:g} s", flush=True)
        return paired({"A": (site_a, False), "B": (site_b, False)}, rounds, windows, seconds, "this tree adds",
                      "issue 49: at most +2")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def paired(sides: dict[str, tuple[str, bool]], rounds: int, windows: int, seconds: float, what: str,
           target: str) -> int:
    """Sides A and B ((site, streams) each) served at the same time, a fresh pair each round; prints each
    window's B − A of the service's CPU (points of one core), per round, overall and per thread."""
    ctx = multiprocessing.get_context("spawn")
    diffs: list[list[float]] = []
    nofit: list[float] = []
    per_thread: dict[str, list[float]] = {}
    own: list[float] = []
    sides_cpu: dict[str, list[float]] = {"A": [], "B": []}
    fits: dict[str, list[float]] = {"A": [], "B": []}
    for r in range(rounds):
        procs, conns, where = {}, {}, {}
        try:
            for side in ("AB" if r % 2 == 0 else "BA"):
                here, there = ctx.Pipe()
                procs[side] = ctx.Process(target=_paired_side, args=(*sides[side], there), daemon=True)
                procs[side].start()
                conns[side] = here
            for side, conn in conns.items():
                got = conn.recv()
                if isinstance(got, BaseException):
                    raise SystemExit(f"bench_server: side {side} did not start: {got}")
                where[side] = got
            round_diffs = []
            for _ in range(windows):
                before = {s: _paired_reading(*where[s]) for s in "AB"}
                time.sleep(seconds)
                after = {s: _paired_reading(*where[s]) for s in "AB"}
                share = {}
                for s in "AB":
                    (c0, th0, f0, w0), (c1, th1, f1, w1) = before[s], after[s]
                    wall = w1 - w0
                    th = {k: 100 * (v - th0.get(k, 0.0)) / wall for k, v in th1.items()}
                    share[s] = (100 * (c1 - c0) / wall, th)
                    sides_cpu[s].append(share[s][0])
                    fits[s].append((f1 - f0) / wall)
                (ca, tha), (cb, thb) = share["A"], share["B"]
                round_diffs.append(cb - ca)
                nofit.append((cb - thb.get("fc-fit", 0.0)) - (ca - tha.get("fc-fit", 0.0)))
                for k in set(tha) | set(thb):
                    per_thread.setdefault(k, []).append(thb.get(k, 0.0) - tha.get(k, 0.0))
                own.append(thb.get("fc-outputs", 0.0))
            diffs.append(round_diffs)
            print(f"  round {r + 1}: B - A per window {' '.join(f'{d:+.1f}' for d in round_diffs)}; median "
                  f"{np.median(round_diffs):+.1f}; A {np.median(sides_cpu['A'][-windows:]):.1f} %, "
                  f"B {np.median(sides_cpu['B'][-windows:]):.1f} %; refits A {np.median(fits['A'][-windows:]):.1f}/s, "
                  f"B {np.median(fits['B'][-windows:]):.1f}/s; load {os.getloadavg()[0]:.1f}", flush=True)
        finally:
            for side, conn in conns.items():
                try:
                    conn.send("stop")
                except OSError:
                    pass
            for p in procs.values():
                p.join(60)
                if p.is_alive():
                    p.terminate()
                    p.join(10)
    every = [d for rd in diffs for d in rd]
    q1, q3 = np.percentile(every, [25, 75])
    print(f"  {what} (B - A, points of one core): median {np.median(every):+.1f} over {len(every)} windows "
          f"(quartiles {q1:+.1f} {q3:+.1f}; round medians {' '.join(f'{np.median(rd):+.1f}' for rd in diffs)}; "
          f"target {target})")
    print(f"  without the fit thread (its CPU follows the refit rate each side got): median {np.median(nofit):+.1f}")
    tops = sorted(per_thread.items(), key=lambda kv: -abs(np.median(kv[1])))
    print("  per thread, median B - A: " + ", ".join(f"{k} {np.median(v):+.1f}" for k, v in tops
                                                    if abs(np.median(v)) >= 0.1))
    if sides["B"][1]:
        print(f"  their thread fc-outputs: median {np.median(own):.1f} % of one core "
              f"(range {min(own):.1f}-{max(own):.1f})")
    return 0
