"""A day at the kiosk in an hour: a real `flockcal serve` (built-in simulator doing the kiosk routine,
tokens, a retention budget small enough to prune during the run) takes guest after guest — start, 20–30 s
of routine, stop, fetch result and skeleton — while a websocket dashboard client and the kiosk page (headless
chromium, read-only token) stay open. Every `--sample-s` it records the service's RSS, Python's live blocks (from
/api/status), open files and threads and the database and data-directory sizes.

Prints sessions per hour, failed requests, the growth of RSS and fds after warm-up and the disk against the
budget as ratios to the targets (issue #19: RSS growth < 10 MB, 0 fds, disk within the budget, 0 failed
requests, every session's result stored), and writes `soak.csv` and `soak.png` (the plot) to --out.

    python benchmarks/bench_soak.py                     # one hour, budget 0.15 GB, two malloc arenas
    python benchmarks/bench_soak.py --minutes 20 --keep-disk 0.05 --no-browser --arena-max 0   # glibc's arenas
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import os
import random
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from flockcal.server.retention import tree_bytes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers
from server_helpers import ServerProcess, free_port, wait_connected  # noqa: E402

ADMIN, READ = "soak-admin-19", "soak-read-19"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
TARGET_RSS_GROWTH_MB = 10.0


def proc_figures(pid: int) -> dict:
    """RSS (MB), threads and open file descriptors of a process, from /proc."""
    fields = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            fields[key] = value.strip()
    return {"rss_mb": int(fields["VmRSS"].split()[0]) / 1024.0, "threads": int(fields["Threads"]),
            "fds": len(os.listdir(f"/proc/{pid}/fd"))}


class Dashboard(threading.Thread):
    """A websocket client subscribed like the dashboard (status, fit, residuals, events), counting
    messages and reconnecting if dropped (each drop counts as a failure)."""

    def __init__(self, url: str):
        super().__init__(daemon=True, name="soak-ws")
        self.url = url.replace("http://", "ws://") + f"/ws/live?token={READ}"
        self.messages = 0
        self.failures: list[str] = []
        self.stop_flag = threading.Event()

    def run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        import websockets

        while not self.stop_flag.is_set():
            try:
                async with websockets.connect(self.url, max_size=None) as ws:
                    await ws.send(json.dumps({"type": "subscribe", "rate_hz": 15,
                                              "content": ["status", "fit", "residuals", "events", "pose"]}))
                    while not self.stop_flag.is_set():
                        try:
                            msg = json.loads(await asyncio.wait_for(ws.recv(), 1.0))
                            self.messages += 1
                            if msg.get("type") == "error":
                                self.failures.append(f"{time.strftime('%H:%M:%S')} websocket error: {msg}")
                        except asyncio.TimeoutError:
                            continue
            except Exception as exc:  # noqa: BLE001 — every way the feed can end is a failure here
                if not self.stop_flag.is_set():
                    self.failures.append(f"{time.strftime('%H:%M:%S')} websocket: {type(exc).__name__}: {exc}")
                    await asyncio.sleep(1.0)


class KioskPage(threading.Thread):
    """The kiosk page in headless chromium with a read-only token (it follows the sessions started here);
    page errors and failed requests of the page count as failures."""

    def __init__(self, url: str):
        super().__init__(daemon=True, name="soak-kiosk")
        self.url = f"{url}/kiosk?token={READ}"
        self.failures: list[str] = []
        self.stop_flag = threading.Event()
        self.seen_states: set[str] = set()
        self.error: str | None = None

    def run(self) -> None:
        try:
            from playwright.sync_api import sync_playwright
        except ImportError as exc:
            self.error = f"no kiosk page: {exc}"
            return
        if not os.path.exists(CHROMIUM):
            self.error = f"no kiosk page: {CHROMIUM} is not installed"
            return
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 800, "height": 600})
            page.on("pageerror", lambda e: self.failures.append(f"{time.strftime('%H:%M:%S')} kiosk page error: {e}"))
            page.on("requestfailed", lambda r: self.failures.append(
                f"{time.strftime('%H:%M:%S')} kiosk request failed: {r.url} {r.failure}"))
            page.goto(self.url)
            while not self.stop_flag.is_set():
                try:
                    self.seen_states.add(page.get_attribute("#kiosk-state", "data-state") or "")
                except Exception as exc:  # noqa: BLE001
                    self.failures.append(f"kiosk page unreadable: {exc}")
                page.wait_for_timeout(1000)
            browser.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--keep-disk", type=float, default=0.15, metavar="GB", help="retention budget (default 0.15 GB)")
    ap.add_argument("--session-s", default="20:30", metavar="LOW:HIGH", help="each guest's time (uniform)")
    ap.add_argument("--sample-s", type=float, default=15.0)
    ap.add_argument("--warmup-min", type=float, default=None, help="default: a tenth of the run, at least 2 min")
    ap.add_argument("--out", type=Path, default=Path("soak-out"))
    ap.add_argument("--no-browser", action="store_true", help="skip the kiosk page")
    ap.add_argument("--arena-max", type=int, default=2, metavar="N",
                    help="MALLOC_ARENA_MAX for the service, as the kiosk's systemd unit sets it (default 2; 0: glibc's own)")
    args = ap.parse_args()
    lo, hi = (float(x) for x in args.session_s.split(":"))
    warmup_s = 60.0 * (args.warmup_min if args.warmup_min is not None else max(2.0, args.minutes / 10.0))
    args.out.mkdir(parents=True, exist_ok=True)
    rng = random.Random(19)
    auth = {"Authorization": f"Bearer {ADMIN}"}
    failures: list[str] = []
    samples: list[dict] = []
    sessions: list[dict] = []

    if args.arena_max > 0:
        os.environ["MALLOC_ARENA_MAX"] = str(args.arena_max)  # the service inherits it (glibc reads it at start)
    else:
        os.environ.pop("MALLOC_ARENA_MAX", None)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        port = free_port()
        device = "sim://soak?birds=16&motion=kiosk&rate=144&baud=921600"
        server = ServerProcess(["--device", device, "--data-dir", str(data), "--token", ADMIN, "--read-token", READ,
                                "--keep-disk", f"{args.keep_disk:g}"], port, log_path=args.out / "serve.log")
        server.start(token=ADMIN)
        url = server.url
        wait_connected(url, token=ADMIN, timeout=60)
        pid = server.proc.pid
        dash = Dashboard(url)
        dash.start()
        kiosk = KioskPage(url)
        if not args.no_browser:
            kiosk.start()
        client = httpx.Client(base_url=url, headers=auth, timeout=60)

        def request(method: str, path: str, **kw):
            try:
                r = client.request(method, path, **kw)
            except httpx.HTTPError as exc:
                failures.append(f"{time.strftime('%H:%M:%S')} {method} {path}: {type(exc).__name__}: {exc}")
                return None
            if r.status_code >= 400:
                failures.append(f"{time.strftime('%H:%M:%S')} {method} {path}: {r.status_code} {r.text[:200]}")
                return None
            return r

        t0 = time.monotonic()
        end = t0 + 60.0 * args.minutes
        next_sample = t0

        def sample() -> None:
            fig = proc_figures(pid)
            db = sum(p.stat().st_size for p in data.glob("flockcal.sqlite3*") if p.is_file())
            st = request("GET", "/api/status")  # the service's own view: Python's live blocks beside RSS
            fig["python_kblocks"] = ((st.json().get("process") or {}).get("python_blocks", 0) / 1e3) if st is not None else None
            samples.append({"t_min": round((time.monotonic() - t0) / 60.0, 3), **fig,
                            "db_mb": db / 1e6, "data_mb": tree_bytes(data) / 1e6, "sessions": len(sessions)})

        while time.monotonic() < end:
            # As the kiosk page starts a guest: the kiosk profile, a lease it renews while the guest moves.
            r = request("POST", "/api/sessions", json={"performer": f"soak guest {len(sessions) + 1}",
                                                       "profile": "kiosk", "lease_s": 30})
            if r is None:
                time.sleep(2.0)
                continue
            sid = r.json()["id"]
            stop_at = time.monotonic() + rng.uniform(lo, hi)
            renewed = time.monotonic()
            while time.monotonic() < stop_at:
                if time.monotonic() >= next_sample:
                    sample()
                    next_sample += args.sample_s
                if time.monotonic() - renewed >= 5.0:
                    request("POST", f"/api/sessions/{sid}/lease")
                    renewed = time.monotonic()
                time.sleep(0.2)
            stopped = request("POST", f"/api/sessions/{sid}/stop")
            result = request("GET", f"/api/sessions/{sid}/result")
            skeleton = request("GET", f"/api/sessions/{sid}/skeleton")
            row = stopped.json() if stopped is not None else {}
            sessions.append({"id": sid, "has_result": bool(row.get("has_result")), "result": result is not None,
                             "skeleton": skeleton is not None, "done": row.get("done"), "frames": row.get("frames")})
            time.sleep(rng.uniform(1.0, 3.0))  # the next guest steps up
        sample()
        status = request("GET", "/api/status")
        stats = request("GET", "/api/stats?days=1")
        listing = request("GET", "/api/sessions")
        dash.stop_flag.set()
        kiosk.stop_flag.set()
        dash.join(10)
        if kiosk.is_alive():
            kiosk.join(30)
        client.close()
        server.stop()

    elapsed_h = (time.monotonic() - t0) / 3600.0
    with open(args.out / "soak.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(samples[0]))
        w.writeheader()
        w.writerows(samples)
    plot(samples, args.out / "soak.png", args.keep_disk * 1000.0, warmup_s / 60.0)

    failures += dash.failures + kiosk.failures
    after = [s for s in samples if s["t_min"] * 60.0 >= warmup_s] or samples
    first, last = after[: max(1, len(after) // 10)], after[-max(1, len(after) // 10):]
    rss_growth = statistics.median(s["rss_mb"] for s in last) - statistics.median(s["rss_mb"] for s in first)
    blocks = [s["python_kblocks"] for s in after if s["python_kblocks"] is not None]
    fd_growth = max(s["fds"] for s in last) - max(s["fds"] for s in first)
    thread_growth = max(s["threads"] for s in last) - max(s["threads"] for s in first)
    disk_max = max(s["data_mb"] for s in samples)
    budget_mb = args.keep_disk * 1000.0
    stored = sum(1 for s in sessions if s["has_result"] and s["result"] and s["skeleton"])
    retention = (status.json().get("retention") if status is not None else None) or {}
    print(f"soak: {elapsed_h * 60:.1f} min, {len(sessions)} sessions ({len(sessions) / elapsed_h:.0f} per hour), "
          f"warm-up {warmup_s / 60:.1f} min, {len(samples)} samples every {args.sample_s:g} s, "
          f"MALLOC_ARENA_MAX={args.arena_max or 'glibc default'}")
    print(f"RSS {samples[0]['rss_mb']:.1f} → {samples[-1]['rss_mb']:.1f} MB, growth after warm-up {rss_growth:+.1f} MB "
          f"({rss_growth / TARGET_RSS_GROWTH_MB:.2f}× the {TARGET_RSS_GROWTH_MB:g} MB limit)")
    if blocks:
        k = max(1, len(blocks) // 10)
        print(f"Python's live blocks after warm-up {statistics.median(blocks[:k]):.0f}k → {statistics.median(blocks[-k:]):.0f}k "
              f"(objects kept grow these; RSS that rises while they stay flat is the allocator)")
    half = [s for s in samples if s["t_min"] >= samples[-1]["t_min"] / 2] or samples
    print(f"RSS over the second half of the run {half[0]['rss_mb']:.1f} → {half[-1]['rss_mb']:.1f} MB "
          f"({half[-1]['rss_mb'] - half[0]['rss_mb']:+.1f} MB over {half[-1]['sessions'] - half[0]['sessions']} sessions): "
          f"a leak grows on, a high-water mark levels off")
    print(f"open files after warm-up {min(s['fds'] for s in after)}–{max(s['fds'] for s in after)}, growth {fd_growth:+d} "
          f"(target 0); threads {min(s['threads'] for s in after)}–{max(s['threads'] for s in after)}, growth {thread_growth:+d}")
    print(f"data directory at most {disk_max:.1f} MB ({disk_max / budget_mb:.2f}× the {budget_mb:g} MB budget; the "
          f"budget is enforced between sessions, so one live session's files may sit on top of it), database at "
          f"most {max(s['db_mb'] for s in samples):.2f} MB")
    print(f"retention: {retention.get('pruned_sessions')} sessions pruned, {retention.get('freed_bytes', 0) / 1e6:.0f} MB "
          f"freed, over budget {retention.get('over_budget')}")
    kept = listing.json()["sessions"] if listing is not None else []
    print(f"results stored: {stored}/{len(sessions)} sessions with result and skeleton fetched after stop; "
          f"{sum(1 for s in kept if s['has_result'])}/{len(kept)} listed with a result at the end; "
          f"calibrated at stop {sum(1 for s in sessions if s['done'])}/{len(sessions)}")
    if stats is not None:
        print(f"/api/stats today: {json.dumps(stats.json()['days'][0])}")
    print(f"dashboard websocket: {dash.messages} messages; kiosk page states seen: "
          f"{', '.join(sorted(x for x in kiosk.seen_states if x)) or kiosk.error or 'none'}")
    print(f"failed requests: {len(failures)}")
    for line in failures[:20]:
        print(f"   {line}")
    print(f"wrote {args.out / 'soak.csv'} and {args.out / 'soak.png'}")


def plot(samples: list[dict], path: Path, budget_mb: float, warmup_min: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [s["t_min"] for s in samples]
    fig, axes = plt.subplots(5, 1, figsize=(9, 12), sharex=True)
    panels = [("rss_mb", "RSS (MB)"), ("python_kblocks", "Python blocks (k)"), ("fds", "open files"), ("threads", "threads")]
    for ax, (key, label) in zip(axes, panels):
        ax.plot(t, [s[key] if s[key] is not None else float("nan") for s in samples], lw=1.2)
        ax.set_ylabel(label)
    axes[4].plot(t, [s["data_mb"] for s in samples], lw=1.2, label="data directory")
    axes[4].plot(t, [s["db_mb"] for s in samples], lw=1.2, label="database")
    axes[4].axhline(budget_mb, color="r", ls="--", lw=1, label="--keep-disk budget")
    axes[4].set_ylabel("MB")
    axes[4].legend(loc="upper left")
    axes[4].set_xlabel("minutes")
    for ax in axes:
        ax.axvline(warmup_min, color="grey", ls=":", lw=1)
        ax.grid(alpha=0.3)
    fig.suptitle("flockcal serve soak: the kiosk flow back to back")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
