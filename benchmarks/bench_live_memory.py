"""One live session held for half an hour: a real `flockcal serve` (built-in simulator, 16 birds at 144 Hz)
records a single session while a websocket dashboard client (status, fit, residuals, events, pose at
15 Hz) stays subscribed. Every `--sample-s` it records the service's RSS, Python's live blocks (from
/api/status) and the sizes of the data folder's parts (frame log, raw recording, database).

Prints the RSS slope after warm-up (least squares, MB an hour) against the target (issue #48: < 4 MB an
hour), and the data folder's growth (GB an hour, by part) against its target (< 0.5 GB an hour); writes
`live_memory.csv` to --out.

    nice -n 10 python benchmarks/bench_live_memory.py                 # 30 minutes, 5 of them warm-up
    nice -n 10 python benchmarks/bench_live_memory.py --rev main      # the service of git revision `main`
    nice -n 10 python benchmarks/bench_live_memory.py --arena-max 2   # two malloc arenas, as the kiosk's unit

With `--rev REV` the service runs the code of revision REV (exported with `git archive`, as
benchmarks/bench_server.py's A/B mode lays it out) instead of this tree's.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers
from bench_server import check_imports, export_revision  # noqa: E402
from bench_soak import ADMIN, READ, Dashboard, proc_figures  # noqa: E402
from server_helpers import ServerProcess, free_port, wait_connected  # noqa: E402

TARGET_RSS_MB_PER_H = 4.0
TARGET_DISK_GB_PER_H = 0.5
PARTS = {"frames": "recordings/*.frames", "raw": "recordings/*.fobraw", "database": "flockcal.sqlite3*"}


def part_bytes(data: Path) -> dict:
    """Bytes of each part of the data folder, and of the whole folder."""
    out = {k: sum(p.stat().st_size for p in data.glob(pattern) if p.is_file()) for k, pattern in PARTS.items()}
    out["total"] = sum(p.stat().st_size for p in data.rglob("*") if p.is_file())
    return out


def slope_per_hour(t_s: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against time, per hour."""
    if len(t_s) < 2:
        return float("nan")
    return float(np.polyfit(t_s / 3600.0, y, 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--warmup-min", type=float, default=5.0)
    ap.add_argument("--sample-s", type=float, default=10.0)
    ap.add_argument("--birds", type=int, default=16)
    ap.add_argument("--rate", type=float, default=144.0)
    ap.add_argument("--motion", default="walk")
    ap.add_argument("--rev", metavar="REV", help="run the service of git revision REV instead of this tree's")
    ap.add_argument("--out", type=Path, default=Path("live-memory-out"))
    ap.add_argument("--arena-max", type=int, default=0, metavar="N",
                    help="MALLOC_ARENA_MAX for the service (default 0: glibc's own, as a plain `flockcal serve`; "
                         "the kiosk's systemd unit sets 2)")
    args = ap.parse_args()
    if args.arena_max > 0:
        os.environ["MALLOC_ARENA_MAX"] = str(args.arena_max)  # the service inherits it (glibc reads it at start)
    else:
        os.environ.pop("MALLOC_ARENA_MAX", None)
    args.out.mkdir(parents=True, exist_ok=True)
    samples: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="flockcal-live-memory-") as tmp:
        cwd = None
        if args.rev:
            site = export_revision(args.rev, os.path.join(tmp, "rev"))
            cwd = os.path.join(tmp, "run")
            os.mkdir(cwd)
            os.environ["PYTHONPATH"] = os.pathsep.join(x for x in (site, os.environ.get("PYTHONPATH")) if x)
            check_imports(site, cwd)
        data = Path(tmp) / "data"
        device = f"sim://live?birds={args.birds}&motion={args.motion}&rate={args.rate:g}&baud=921600"
        server = ServerProcess(["--device", device, "--data-dir", str(data), "--token", ADMIN, "--read-token", READ],
                               free_port(), log_path=args.out / "serve.log", cwd=cwd)
        server.start(token=ADMIN)
        auth = {"Authorization": f"Bearer {ADMIN}"}
        client = httpx.Client(base_url=server.url, headers=auth, timeout=60)
        dash = None
        try:
            wait_connected(server.url, token=ADMIN, timeout=60)
            dash = Dashboard(server.url)
            dash.start()
            r = client.post("/api/sessions", json={"performer": "soak", "profile": "stage"})
            r.raise_for_status()
            sid = r.json()["id"]
            load0 = os.getloadavg()
            t0 = time.monotonic()
            end = t0 + 60.0 * args.minutes
            next_sample = t0
            while True:
                now = time.monotonic()
                if now >= next_sample:
                    fig = proc_figures(server.proc.pid)
                    st = client.get("/api/status").json()
                    frames = (st.get("session") or {}).get("frames")
                    samples.append({"t_s": round(now - t0, 2), "rss_mb": fig["rss_mb"], "threads": fig["threads"],
                                    "fds": fig["fds"], "python_blocks": (st.get("process") or {}).get("python_blocks"),
                                    "frames": frames, "load1": os.getloadavg()[0],
                                    **{f"{k}_bytes": v for k, v in part_bytes(data).items()}})
                    next_sample += args.sample_s
                if now >= end:
                    break
                time.sleep(max(0.0, min(next_sample, end) - time.monotonic()))
            stopped = client.post(f"/api/sessions/{sid}/stop").json()
            kept = client.get("/api/status").json().get("retention") or {}  # its heap trims (None before them)
            load1 = os.getloadavg()
        finally:
            if dash is not None:
                dash.stop_flag.set()
                dash.join(10)
            client.close()
            server.stop()

    with open(args.out / "live_memory.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(samples[0]))
        w.writeheader()
        w.writerows(samples)

    t = np.array([s["t_s"] for s in samples])
    after = t >= 60.0 * args.warmup_min
    rss = np.array([s["rss_mb"] for s in samples])
    blocks = np.array([s["python_blocks"] or np.nan for s in samples], dtype=float)
    rss_slope = slope_per_hour(t[after], rss[after])
    block_slope = slope_per_hour(t[after], blocks[after] / 1e3)
    minutes = t[-1] / 60.0
    print(f"live session: {minutes:.1f} min, {args.birds} birds at {args.rate:g} Hz ({args.motion}), "
          f"{stopped.get('frames')} frames, dashboard websocket {dash.messages} messages, "
          f"{len(dash.failures)} websocket failures; service: {'revision ' + args.rev if args.rev else 'this tree'}, "
          f"MALLOC_ARENA_MAX={args.arena_max or 'glibc default'}")
    print(f"load average (1, 5, 15 min) at the start {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, at the end "
          f"{load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}, 1-min mean over the samples {np.mean([s['load1'] for s in samples]):.2f} "
          f"({os.cpu_count()} cores)")
    print(f"RSS {rss[0]:.1f} → {rss[after][0]:.1f} MB at the end of the {args.warmup_min:g}-min warm-up → {rss[-1]:.1f} MB; "
          f"slope after warm-up {rss_slope:+.1f} MB an hour ({rss_slope / TARGET_RSS_MB_PER_H:.2f}× the "
          f"{TARGET_RSS_MB_PER_H:g} MB/h target)")
    # Where it flattens: the slope over each later stretch (a session behind its tracker on a loaded machine
    # fills its windows later than the wall clock says).
    edges = [args.warmup_min] + [m for m in (10.0, 20.0) if args.warmup_min < m < minutes] + [minutes]
    parts = []
    for a, b in zip(edges[:-1], edges[1:]):
        w = (t >= 60.0 * a) & (t <= 60.0 * b + 1.0)
        parts.append(f"{a:g}–{b:.0f} min {slope_per_hour(t[w], rss[w]):+.1f}")
    done = np.array([s["frames"] or 0 for s in samples], dtype=float)
    at_warm = done[after][0] / (60.0 * args.warmup_min * args.rate)
    print(f"RSS slope by stretch (MB an hour): {', '.join(parts)}; the session had taken in {at_warm:.0%} of "
          f"{args.warmup_min:g} min of frames when the warm-up ended")
    print(f"Python's live blocks after warm-up {blocks[after][0] / 1e3:.0f}k → {blocks[-1] / 1e3:.0f}k "
          f"({block_slope:+.1f}k an hour)")
    if kept.get("heap_trims") is not None:
        mean = kept.get("heap_trim_ms_mean")
        print(f"heap trims (malloc_trim on the housekeeping thread): {kept['heap_trims']}, "
              f"{'-' if mean is None else f'{mean:.1f}'} ms mean, {kept['heap_trim_ms_max']:.1f} ms longest")
    rows = []
    for part in ("frames", "raw", "database", "total"):
        y = np.array([s[f"{part}_bytes"] for s in samples], dtype=float)
        rows.append((part, slope_per_hour(t[t >= 60.0], y[t >= 60.0]) / 1e9, y[-1] / 1e6))
    print("data folder growth: " + ", ".join(f"{part} {gb:.3f} GB/h ({mb:.0f} MB at the end)" for part, gb, mb in rows)
          + f"; total {rows[-1][1] / TARGET_DISK_GB_PER_H:.2f}× the {TARGET_DISK_GB_PER_H:g} GB/h target")
    if stopped.get("frames"):
        print(f"frame log {samples[-1]['frames_bytes'] / max(samples[-1]['frames'] or 1, 1):.0f} bytes a frame "
              f"({args.birds} birds)")
    for line in dash.failures[:10]:
        print(f"   {line}")
    print(f"wrote {args.out / 'live_memory.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
