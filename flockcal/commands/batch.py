"""`flockcal batch TAKE... -o DIR`: fit many takes in parallel on Dask, one `fit --json` result each, a
summary.csv, and with --combine one calibration from all of a performer's takes (design.md §5).

The client expands the inputs, starts (or joins) the cluster, writes DIR; workers read the takes and fit
them (flockcal/commands/batch_tasks.py), so the takes must be at the same paths on every worker.
"""

from __future__ import annotations

import argparse
import csv
import glob
import io
import logging
import os
import sys
import time
import uuid
from operator import itemgetter
from pathlib import Path

from flockcal.commands.batch_tasks import SUFFIXES, FitOptions, TakeOutcome, one_line, warm_up
from flockcal.commands.fit import add_tolerance, load_hierarchy, tolerance_m
from flockcal.errors import UserError

INSTALL_HINT = "pip install 'flockcal[batch]'"
SUMMARY_COLUMNS = ("take", "frames", "sensors", "root", "joints_determined", "worst_rms_mm", "slips", "seconds",
                   "error")
# Per-take sums for --combine are folded together on the workers in groups of this many as takes finish,
# so a thousand takes never hold a thousand accumulators at once.
FOLD = 8
CONNECT_TIMEOUT_S = 20.0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch",
        help="fit many takes in parallel on Dask (a local cluster or an existing one)",
        description="Fit every take given (files, folders, globs: .npz, .fobraw, .c3d) on a Dask cluster: "
                    "DIR/<stem>.json is what `flockcal fit TAKE --json` prints (`fit-markers --json` for "
                    "marker takes), DIR/summary.csv has one row per take. Exit status 1 when any take failed.",
    )
    p.add_argument("takes", nargs="+", metavar="TAKE", help="take files, folders of takes, or quoted globs")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the results (made if missing)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="worker processes of the local Dask cluster (default: one per core)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing dask.distributed cluster, e.g. tcp://10.0.0.5:8786")
    p.add_argument("--timeout", type=float, default=CONNECT_TIMEOUT_S, metavar="S",
                   help=f"with --scheduler: seconds to wait for it and for a worker (default {CONNECT_TIMEOUT_S:g})")
    p.add_argument("--combine", action="store_true",
                   help="also fit one calibration from all takes (their sums added; same sensors): DIR/combined.json")
    p.add_argument("--hierarchy", metavar="MAP.json", help="as for `flockcal fit` (sensor takes)")
    p.add_argument("--root", metavar="NAME", help="as for `flockcal fit` and `fit-markers`")
    p.add_argument("--no-slips", action="store_true", help="as for `flockcal fit`: skip the slip search")
    p.add_argument("--allow-partial", action="store_true",
                   help="fit takes that are too short or too still anyway (as `flockcal fit --allow-partial`)")
    add_tolerance(p)
    p.set_defaults(func=run)


# -- inputs --------------------------------------------------------------------------------------------


def expand(items: list[str]) -> list[tuple[str, str]]:
    """(name as given, absolute path) per take: folders searched recursively for take files, globs
    expanded (`**` too), each file once. A path that does not exist, and a folder or glob with no take
    in it, is a UserError naming it: a usage error, found before any cluster starts."""
    out: list[tuple[str, str]] = []
    seen: set[str] = set()

    def add(name: str) -> None:
        full = os.path.abspath(name)
        if full not in seen:
            seen.add(full)
            out.append((name, full))

    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(str(f) for f in p.rglob("*") if f.is_file() and f.suffix.lower() in SUFFIXES)
            if not found:
                raise UserError(nothing_found(item))
            for f in found:
                add(f)
        elif glob.has_magic(item) and not p.exists():
            found = sorted(glob.glob(item, recursive=True))
            files = [f for f in found if Path(f).is_file() and Path(f).suffix.lower() in SUFFIXES]
            for d in (f for f in found if Path(f).is_dir()):
                files += sorted(str(f) for f in Path(d).rglob("*") if f.is_file() and f.suffix.lower() in SUFFIXES)
            if not files:
                raise UserError(nothing_found(item))
            for f in files:
                add(f)
        elif not p.exists():
            raise UserError(f"{item}: no such file or folder; check the path (folders and quoted globs are "
                            "searched for takes)")
        else:
            add(item)  # an unreadable file or one that is not a take is reported in its row by the worker
    return out


def nothing_found(item: str) -> str:
    kinds = ", ".join(SUFFIXES)
    if Path(item).is_dir():
        return f"{item}: no take ({kinds}) in this folder or below it; give the folder that holds the takes"
    return f"{item}: no take file ({kinds}) matches; check the pattern"


def check_names(takes: list[tuple[str, str]], combine: bool) -> None:
    """Every take must have its own DIR/<stem>.json: two takes of one stem would overwrite each other."""
    stems: dict[str, str] = {}
    reserved = {"combined"} if combine else set()
    for name, path in takes:
        stem = Path(path).stem
        if stem in reserved:
            raise UserError(f"{name} would write DIR/combined.json, which --combine writes; rename the take")
        if stem in stems:
            raise UserError(f"{stems[stem]} and {name} would both write DIR/{stem}.json; rename one, or run "
                            "them in separate batches")
        stems[stem] = name


# -- the cluster ---------------------------------------------------------------------------------------


def import_dask():
    """dask.distributed, or a one-line error naming the extra to install."""
    try:
        import distributed  # noqa: F401
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as exc:
        raise UserError(f"flockcal batch runs on Dask, which is not installed ({exc.name} is missing): "
                        f"{INSTALL_HINT}") from None
    return Client, LocalCluster, as_completed


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def start_client(args: argparse.Namespace, n_takes: int):
    """(client, cluster or None, where) for --scheduler or a new LocalCluster."""
    if args.scheduler:
        from flockcal.commands.scheduler_probe import check_scheduler

        # On a plain socket first: Dask's client, pointed at something else, can hang past its timeout.
        check_scheduler(args.scheduler, args.timeout)
    Client, LocalCluster, _ = import_dask()
    if not getattr(args, "verbose", 0):
        # The scheduler of a local cluster runs in this process and logs every worker it registers.
        logging.getLogger("distributed").setLevel(logging.ERROR)
    if args.scheduler:
        try:
            client = Client(args.scheduler, timeout=args.timeout)
        except (OSError, TimeoutError, ValueError, MemoryError) as exc:  # MemoryError: a peer's garbage as a length
            raise UserError(f"cannot reach the Dask scheduler at {args.scheduler} ({' '.join(str(exc).split())}); "
                            "start one with `dask scheduler` and give its tcp://host:port") from None
        try:
            check_workers(client, args.scheduler, args.timeout)
        except BaseException:
            client.close()
            raise
        return client, None, f"the cluster at {args.scheduler}"
    n = default_workers() if args.workers is None else args.workers
    n = min(n, max(1, n_takes))  # an idle worker process costs start-up time and memory, nothing more
    # One thread per process: the fit holds the GIL between its numpy calls, so processes, not threads,
    # give parallel takes. The dashboard listens on loopback, on a free port.
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                           silence_logs=logging.ERROR)
    try:
        client = Client(cluster)
    except BaseException:
        cluster.close()
        raise
    return client, cluster, f"a local cluster of {n} worker process{'es' if n > 1 else ''}"


def check_workers(client, address: str, timeout: float) -> None:
    """The cluster has workers, and each runs this flockcal (they import its code to fit the takes)."""
    import importlib.metadata

    try:
        client.wait_for_workers(1, timeout=timeout)
    except (TimeoutError, OSError):
        raise UserError(f"the Dask scheduler at {address} has no workers; start some with "
                        f"`dask worker {address}` on machines with {INSTALL_HINT}") from None
    mine = importlib.metadata.version("flockcal")
    try:
        theirs = client.run(importlib.metadata.version, "flockcal")
    except Exception:  # noqa: BLE001 — any failure here means a worker lacks the package
        raise UserError(f"a worker of {address} cannot find flockcal: {INSTALL_HINT} on every worker machine") from None
    other = {w: v for w, v in theirs.items() if v != mine}
    if other:
        w, v = next(iter(other.items()))
        raise UserError(f"worker {w} runs flockcal {v}, this is flockcal {mine}: install the same version on "
                        "every worker (results must be what this `flockcal fit` prints)")


def dashboard(client) -> str | None:
    """The Dask dashboard's address when the scheduler runs one (it needs bokeh)."""
    try:
        services = client.scheduler_info().get("services", {})
    except Exception:  # noqa: BLE001 — the address is a courtesy, never a reason to fail
        return None
    return client.dashboard_link if "dashboard" in services else None


# -- the run -------------------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> int:
    # Inputs and options first, then Dask, then the cluster: a usage error is reported as one, at once,
    # with or without Dask installed, and nothing is written or started for it.
    if not args.timeout > 0:
        raise UserError(f"--timeout must be a positive number of seconds, got {args.timeout}")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be 1 or more, got {args.workers}")
    options = FitOptions(
        hierarchy=load_hierarchy(args.hierarchy) if args.hierarchy else None,
        root=args.root,
        tolerance=tolerance_m(args),
        find_slips=not args.no_slips,
        allow_partial=args.allow_partial,
        combine=args.combine,
    )
    takes = expand(args.takes)
    check_names(takes, args.combine)
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"-o {out_dir}: that is a file; give a folder for the results")
    import_dask()  # without Dask the command says what to install
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"-o {out_dir}: cannot make the output folder ({exc.strerror})") from None
    todo = takes  # expand() found at least one take, or said why not
    outcomes: dict[str, TakeOutcome] = {}
    combined_ok = True
    if todo:
        started = time.perf_counter()
        client, cluster, where = start_client(args, len(todo))
        try:
            # Imported on every worker before the first take, so a take's seconds are its fit, not start-up.
            client.run(warm_up)
            up = time.perf_counter() - started
            print(f"flockcal batch: {len(todo)} take{'s' if len(todo) != 1 else ''} on {where} (ready in {up:.1f} s)",
                  file=sys.stderr)
            link = dashboard(client)
            if link:
                print(f"flockcal batch: Dask dashboard at {link}", file=sys.stderr)
            combined_ok = fit_all(client, todo, options, out_dir, outcomes)
            print(f"flockcal batch: fitted in {time.perf_counter() - started - up:.1f} s", file=sys.stderr)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    rows = [outcomes[name] for name, _ in takes]
    write_summary(out_dir / "summary.csv", rows)
    failed = [r for r in rows if r.error]
    print(f"flockcal batch: {len(rows) - len(failed)} of {len(rows)} takes fitted; wrote {out_dir}/summary.csv"
          + (f" ({len(failed)} failed, named there)" if failed else ""), file=sys.stderr)
    return 1 if failed or not combined_ok else 0


def fit_all(client, todo: list[tuple[str, str]], options: FitOptions, out_dir: Path,
            outcomes: dict[str, TakeOutcome]) -> bool:
    """Fit every take on the cluster, writing each result as it arrives; with --combine, fold the takes'
    sums on the workers and write combined.json. False when --combine could not produce one."""
    from dask.distributed import as_completed

    from flockcal.atomic import write_atomic
    from flockcal.commands import batch_tasks as tasks
    from flockcal.bars import bar

    run_id = uuid.uuid4().hex[:8]  # keys unique to this run: other batches may share the scheduler
    origin = None
    if options.combine:
        origin = client.submit(tasks.shared_origin, [p for _, p in todo], key=f"flockcal-origin-{run_id}")
    # `fits` holds each fit's future until its row is read: the row and the sum are picked from it on the
    # worker that holds it, so only the row (and the JSON text) travels to this process.
    fits, rows, sums = {}, {}, {}
    for k, (name, path) in enumerate(todo):
        f = client.submit(tasks.fit_one, path, options, origin, key=f"flockcal-fit-{run_id}-{k}")
        rows[client.submit(itemgetter(0), f, key=f"flockcal-row-{run_id}-{k}")] = name
        if options.combine:
            sums[name] = client.submit(itemgetter(1), f, key=f"flockcal-sum-{run_id}-{k}")
        fits[name] = f
    groups: dict[tuple, list] = {}  # names → [folded sum futures]; counts → takes in each
    counts: dict[tuple, list[str]] = {}
    left_out: list[dict] = []  # takes --combine leaves out, with the reason
    with bar(len(rows), "fitting", unit="take") as shown:
        for fut in as_completed(list(rows)):
            name = rows[fut]
            try:
                res = fut.result()
                res.path = name
            except Exception as exc:  # noqa: BLE001 — a worker that died takes only its take down
                res = TakeOutcome(name, error=worker_failure(exc))
            fits.pop(name, None)
            outcomes[name] = res
            if res.text is not None:
                write_atomic(out_dir / f"{Path(name).stem}.json", res.text)
            if res.warning:
                print(f"flockcal batch: warning: {name} is {res.warning}; fitted anyway (--allow-partial)",
                      file=sys.stderr)
            if options.combine:
                s = sums.pop(name)
                if res.error:
                    left_out.append({"take": name, "reason": f"it failed: {res.error}"})
                elif res.kind != "sensors":
                    left_out.append({"take": name, "reason": "a marker take: --combine sums sensor takes"})
                else:
                    g = groups.setdefault(res.names, [])
                    counts.setdefault(res.names, []).append(name)
                    g.append(s)
                    if len(g) >= FOLD:
                        key = f"flockcal-fold-{run_id}-{uuid.uuid4().hex[:8]}"
                        groups[res.names] = [client.submit(tasks.merged, *g, key=key)]
            shown.update(1)
    if not options.combine:
        return True
    return combine(client, todo, options, out_dir, groups, counts, left_out, run_id)


def combine(client, todo, options: FitOptions, out_dir: Path, groups: dict, counts: dict, left_out: list,
            run_id: str) -> bool:
    """Write combined.json from the largest group of takes sharing one sensor list; name the rest."""
    from flockcal.atomic import write_atomic
    from flockcal.commands import batch_tasks as tasks

    if not counts:
        print("flockcal batch: error: --combine: no take fitted, so there is nothing to combine", file=sys.stderr)
        return False
    first = {name: k for k, (name, _) in enumerate(todo)}
    # The performer's sensor list is the one most takes share (the first take's on a tie).
    names = max(counts, key=lambda n: (len(counts[n]), -min(first[t] for t in counts[n])))
    for other, takes in counts.items():
        if other != names:
            for t in takes:
                left_out.append({"take": t, "reason": f"its sensors ({', '.join(other)}) differ from the combined "
                                                      f"takes' ({', '.join(names)})"})
    order = {name: k for k, (name, _) in enumerate(todo)}
    left_out.sort(key=lambda e: order.get(e["take"], -1))
    combined = sorted(counts[names], key=order.get)
    g = groups[names]
    total = g[0] if len(g) == 1 else client.submit(tasks.merged, *g, key=f"flockcal-fold-{run_id}-final")
    try:
        text = client.submit(tasks.combined_text, total, names, options, combined, left_out,
                             key=f"flockcal-combined-{run_id}").result()
    except Exception as exc:  # noqa: BLE001 — the per-take results stand; the combined fit is reported
        print(f"flockcal batch: error: --combine: {one_line(exc)}", file=sys.stderr)
        return False
    write_atomic(out_dir / "combined.json", text)
    for e in left_out:
        print(f"flockcal batch: --combine left out {e['take']}: {e['reason']}", file=sys.stderr)
    print(f"flockcal batch: combined {len(combined)} take{'s' if len(combined) != 1 else ''} into "
          f"{out_dir}/combined.json", file=sys.stderr)
    return True


def worker_failure(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if type(exc).__name__ == "KilledWorker":
        return f"the worker fitting it died (out of memory, or killed): {text}"
    return one_line(exc)


def write_summary(path: Path, rows: list[TakeOutcome]) -> None:
    from flockcal.atomic import write_atomic

    def num(x, digits=None):
        if x is None:
            return ""
        return f"{x:.{digits}f}" if digits is not None else str(x)

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SUMMARY_COLUMNS)
    for r in rows:
        w.writerow([r.path, num(r.frames), num(r.sensors), r.root or "", num(r.determined),
                    num(r.worst_rms_mm, 3), num(r.slips), f"{r.seconds:.3f}", r.error])
    write_atomic(path, buf.getvalue())
