"""One self-contained HTML report of a calibration: skeleton drawing, bones, topology, calibration progress
(the service's one definition), per-joint residual plots and histograms (the paper's figures 6–8),
coverage and slip events. Figures are base64 PNG data URIs, so the page is a single file that opens anywhere.
"""

from __future__ import annotations

import base64
import html
import io
import os
import warnings
from dataclasses import fields, replace
from datetime import datetime, timezone

import numpy as np

from flockcal.atomic import write_atomic
from flockcal.solver.calibration import Calibration
from flockcal.solver.fits import PairFits
from flockcal.solver.progress import JointProgress, Progress
from flockcal.solver.reconstruct import Articulation, articulation, reconstruct, tree_residuals

MAX_PLOT_POINTS = 4000  # per joint trace: enough to see every burst, small enough to draw quickly

CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em} h2{margin-top:1.8em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0} td,th{padding:2px 10px;border-bottom:1px solid #eee;text-align:right}
th{background:#f4f4f4} td.name,th.name{text-align:left} .meta{color:#666}
.bar{display:inline-block;height:10px;background:#3a7;vertical-align:middle}
.barbox{display:inline-block;width:60px;background:#eee;margin-right:4px}
img{max-width:100%;border:1px solid #ddd} ul.tree{list-style:none;padding-left:1.2em}
"""


def _png(fig) -> str:
    """The figure as a data: URI (and the figure closed, so long reports do not pile up memory)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(uri: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="{uri}">'


def _pose_frame(valid: np.ndarray) -> int:
    """A frame to draw: the middle of the take, moved to the nearest frame where every sensor is valid."""
    n = len(valid)
    full = np.flatnonzero(valid.all(axis=1))
    if not len(full):
        return n // 2
    return int(full[np.argmin(np.abs(full - n // 2))])


def skeleton_figure(rec, frame: int, world: np.ndarray, determined=None) -> str:
    """Three orthographic views of the reconstructed pose at `frame`: bones solid, sensor offsets dashed.

    `world` turns tracker coordinates into a Y-up frame (see `bvh.bvh_world`): x, up, z. `determined`
    ((m,) bool, by body): a body whose inboard joint is not determined is joined by a thin dotted line, not
    a bone, and its joint drawn hollow (docs/design.md §3a); None draws every joint as determined.
    """
    import matplotlib.pyplot as plt

    art = rec.articulation
    J = rec.joint_positions[frame] @ world.T
    S = rec.sensor_positions[frame] @ world.T
    views = [("front (z, up)", 2, 1), ("side (x, up)", 0, 1), ("top (x, z)", 0, 2)]
    ok = np.ones(art.n_bodies, dtype=bool) if determined is None else np.asarray(determined, dtype=bool)
    ok = ok | (np.arange(art.n_bodies) == art.root)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.4))
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.08, top=0.86, wspace=0.22)
    for ax, (title, a, b) in zip(axes, views):
        for j in art.order[1:]:
            p = art.parent[j]
            bone = ok[j] and ok[p]
            ax.plot([J[p, a], J[j, a]], [J[p, b], J[j, b]], "-" if bone else ":", color="#246" if bone else "#999",
                    lw=2.5 if bone else 1.0)
        for j in range(art.n_bodies):
            ax.plot([J[j, a], S[j, a]], [J[j, b], S[j, b]], "--", color="#c63", lw=0.8)
        ax.plot(J[ok, a], J[ok, b], "o", color="#246", ms=4)
        ax.plot(J[~ok, a], J[~ok, b], "o", mfc="none", color="#999", ms=5)
        ax.plot(S[:, a], S[:, b], "s", color="#c63", ms=3)
        for j, name in enumerate(art.names):
            ax.annotate(name, (J[j, a], J[j, b]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.suptitle(f"reconstructed pose at frame {frame} (joints ●, not determined ○, sensors ■)", fontsize=11)
    return _png(fig)


def _grid(k: int):
    import matplotlib.pyplot as plt

    cols = 3 if k > 4 else max(k, 1)
    rows = max(1, -(-k // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.3 * rows), squeeze=False)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.5 / rows, top=1 - 0.35 / rows, hspace=0.55, wspace=0.18)
    for ax in axes.flat[k:]:
        ax.axis("off")
    return fig, axes.flat


def residual_time_figure(times, e, joints, names) -> str:
    """Per joint: residual components and magnitude (mm) against time (paper figs 6–7)."""
    fig, axes = _grid(len(joints))
    step = max(1, len(times) // MAX_PLOT_POINTS)
    t = times[::step]
    for ax, j in zip(axes, joints):
        ej = e[::step, j] * 1000
        for k, (axis, colour) in enumerate(zip("xyz", ("#d55", "#5a5", "#55d"))):
            ax.plot(t, ej[:, k], lw=0.6, color=colour, label=axis)
        ax.plot(t, np.linalg.norm(ej, axis=1), lw=0.9, color="k", label="|e|")
        ax.set_title(f"{names[j]}", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6, ncol=4, loc="upper right")
    fig.supxlabel("time (s)", fontsize=9)
    fig.supylabel("residual (mm)", fontsize=9)
    return _png(fig)


def residual_histogram_figure(sep, joints, names) -> str:
    """Per joint: histogram of the residual magnitude (mm) over all frames (paper fig 8)."""
    fig, axes = _grid(len(joints))
    for ax, j in zip(axes, joints):
        s = sep[:, j]
        s = s[np.isfinite(s)] * 1000
        if len(s):
            counts, edges = np.histogram(s, bins=40)
            ax.stairs(counts, edges, fill=True, color="#468")  # one artist, not 40 bars: quick to draw
            ax.axvline(np.sqrt(np.mean(s**2)), color="#c33", lw=1)
        ax.set_title(f"{names[j]}", fontsize=9)
        ax.tick_params(labelsize=7)
    fig.supxlabel("|residual| (mm); red line: rms", fontsize=9)
    fig.supylabel("frames", fontsize=9)
    return _png(fig)


def _fmt(x, scale=1.0, digits=1) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{float(x) * scale:.{digits}f}"


def _tree_html(art: Articulation, rms_by_child: dict[str, float], standing: dict[str, JointProgress],
               bones: dict[str, str] | None = None, joint_names: dict[str, str] | None = None) -> str:
    bones, joint_names = bones or {}, joint_names or {}

    def node(i: int) -> str:
        name = art.names[i]
        label = html.escape(name) + (f" <b>[{html.escape(bones[name])}]</b>" if name in bones else "")
        if art.parent[i] >= 0:
            said = f"{html.escape(joint_names[name])}: " if name in joint_names else ""
            label += f" <span class=meta>({said}joint rms {_fmt(rms_by_child.get(name), 1000, 2)} mm"
            st = standing.get(art.names[i])
            if st and not st.done:
                label += f"; not calibrated: {html.escape(st.why or st.state.value)}"
            label += ")</span>"
        kids = "".join(node(k) for k in art.children(i))
        return f"<li>{label}{f'<ul class=tree>{kids}</ul>' if kids else ''}</li>"

    return f"<ul class=tree>{node(art.root)}</ul>"


def _bars(cov) -> str:
    if cov is None:
        return "–"
    vals = [float(v) if v is not None else float("nan") for v in cov]
    bars = "".join(
        f'<span class=barbox title="{v:.3f}"><span class=bar style="width:{60 * min(max(v, 0), 1):.0f}px"></span></span>'
        for v in np.nan_to_num(vals)
    )
    return bars + " ".join(_fmt(v, 1, 2) for v in vals)


class Text(str):
    """A table cell of plain text, escaped and left-aligned (numbers are right-aligned, HTML kept)."""


def _table(headers: list[str], rows: list[list]) -> str:
    """An HTML table; a header starting with "<" or a `Text` cell is a left-aligned name column."""

    def cell(tag: str, value) -> str:
        if isinstance(value, Text):
            return f"<{tag} class=name>{html.escape(value)}</{tag}>"
        return f"<{tag}>{value}</{tag}>"

    head = "".join(f"<th class=name>{h[1:]}</th>" if h.startswith("<") else f"<th>{h}</th>" for h in headers)
    body = "".join("<tr>" + "".join(cell("td", v) for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _find_slips(take, cal: Calibration) -> list:
    """Slip events: the calibration's own, else the slippage detector's over the take."""
    if cal.slip_events:
        return list(cal.slip_events)
    from flockcal.solver.slippage import detect_slips

    return list(detect_slips(take, cal))


def _longest_gap_s(valid: np.ndarray, rate_hz: float) -> np.ndarray:
    """(m,) longest run of invalid frames per sensor, in seconds."""
    out = []
    for v in valid.T:  # one pass per sensor (m ≤ 16), vectorised over frames
        gaps = np.diff(np.flatnonzero(np.concatenate([[True], v, [True]]))) - 1
        out.append(gaps.max() if len(gaps) else 0)
    return np.asarray(out, dtype=float) / rate_hz


REPORT_STAGES = ("residuals", "slips", "figures")


def joined_forest(cal: Calibration, take) -> Calibration:
    """An optical fit's forest (bodies no exercised joint reaches hang from nothing) made one tree for the
    page: each part's root hangs from the main root by the plain least-squares joint of the two bodies'
    poses, marked undetermined (drawn dotted, listed as unjoined). A tree is returned as it is."""
    names = list(cal.names)
    loose = [i for i in range(len(names)) if i != cal.root and cal.parent[i] < 0]
    if not loose:
        return cal
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import pair_fits

    idx = [take.names.index(n) for n in names]
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    pf = pair_fits(acc, np.array([[idx[x], idx[cal.root]] for x in loose]))
    none = np.full(len(loose), np.nan)  # a stand-in's own statistics are not the page's: its rms is measured below
    added = replace(pf, pairs=np.array([[x, cal.root] for x in loose]), hinge=np.zeros(len(loose), dtype=bool),
                    determined=np.zeros(len(loose), dtype=bool), epsilon=none, c_stderr=none)
    joints = PairFits(*(np.concatenate([getattr(cal.joints, f.name), getattr(added, f.name)])
                        for f in fields(PairFits)))
    parent = cal.parent.copy()
    parent[loose] = cal.root
    optical = cal.optical
    if optical is not None:  # what the page reads of each added joint: not determined, no Kirk fit
        optical = replace(optical, kirk_rms=np.concatenate([optical.kirk_rms, np.full(len(loose), np.nan)]),
                          joint_decisions=tuple(optical.joint_decisions) + ({"determined": False,
                                                                             "direction_error_m": None},) * len(loose))
    return replace(cal, parent=parent, joints=joints, optical=optical,
                   order=np.concatenate([cal.order, [x for x in loose if x not in cal.order]]).astype(int))


def optical_html(cal: Calibration) -> str:
    """What a marker fit adds: its bodies and their markers, which groups of markers were merged into one
    body and why, the joints fitted on part of a body, the bodies no exercised joint reaches."""
    d = cal.optical.exercise  # the optical fit's exercise report (solver/optical/pipeline.py)
    parents = cal.parent_map()
    motion = d.get("body_motion_m", {})
    unjoined = set(d.get("unjoined", []))
    rows = [[Text(b), Text(parents.get(b, "–") if b not in unjoined else "unjoined"), _fmt(motion.get(b), 1000, 1),
             Text(", ".join(m))] for b, m in cal.optical.bodies.items()]
    out = ["<h2>Bodies from the markers</h2>",
           f"<p class=meta>Two groups of markers are two bodies when a joint explains their relative motion, "
           f"however small; one body when they turned no more than their own soft tissue turns them, or barely "
           f"moved (within {_fmt(d.get('rigid_tolerance_m'), 1000, 0)} mm) with no joint pinned "
           f"(docs/optical.md, \"Segmentation\"). Internal motion: the mean 10–90 % range of the distances "
           f"between a body's markers.</p>",
           _table(["<body", "<parent", "internal motion (mm)", "<markers"], rows)]
    merged = d.get("merged") or {}
    out.append("<h3>Merged, and why</h3>")
    if not merged:
        out.append("<p>No body was made of groups of three or more markers that could have been bodies of their own.</p>")
    for body, info in merged.items():
        parts = info.get("parts") or []
        out.append(f"<p><b>{html.escape(body)}</b>: {len(parts)} rigid part{'s' if len(parts) != 1 else ''} "
                   f"({'; '.join(html.escape(', '.join(p)) for p in parts)})</p><ul>")
        for mg in info.get("merges", []):
            a, b = (", ".join(g) for g in mg["groups"])
            out.append(f"<li>{html.escape(a)} + {html.escape(b)}: {html.escape(mg['why'])}</li>")
        out.append("</ul>")
    fitted = d.get("joints_fitted_on") or []
    if fitted:
        out.append("<h3>Joints fitted on part of a body</h3><p class=meta>A joint to a body that absorbed several "
                   "segments is fitted on its rigid part next to the other body, not the whole.</p>")
        out.append(_table(["<joint", "<child's markers", "<parent's markers"],
                          [[Text(" – ".join(f["joint"])), Text(", ".join(f["child_markers"])),
                            Text(", ".join(f["parent_markers"]))] for f in fitted]))
    if unjoined:
        out.append(f"<p>No exercised joint reaches {html.escape(', '.join(sorted(unjoined)))}: drawn dotted from the root "
                   "(its plain least-squares joint, not a bone).</p>")
    return "\n".join(out)


def report_html(
    calibration, take, *, title: str | None = None, source: str | None = None, slips=None, up: str = "-z",
    progress=None,
) -> str:
    """The report page for `take` (a flockcal.takes.Take) fitted as `calibration` (Calibration or its
    §5 dict). `slips` overrides the slip events (list of §5 slip dicts); `up` is the world's up axis;
    `progress(stage)` is told each of REPORT_STAGES as it begins (for a progress bar)."""
    step = progress or (lambda stage: None)
    import matplotlib

    matplotlib.use("Agg")
    from flockcal.exports.bvh import bvh_world
    from flockcal.solver.calibration_json import as_calibration
    from flockcal.solver.fits import TOLERANCE_M
    from flockcal.solver.known_skeleton import bone_arrays
    from flockcal.solver.progress import default_target, progress_of

    step(REPORT_STAGES[0])
    # A §5 dict (a fit written out) is decoded once, by the one parser; everything below reads the typed fit.
    cal = as_calibration(calibration)
    given = isinstance(calibration, Calibration) and calibration.hierarchy_given  # a file says not
    optical = cal.optical is not None
    # Each joint as people name it (the stand-ins an optical forest is joined with below have no name).
    joint_names = dict(zip((cal.names[c] for c in cal.joint_child.tolist()), cal.joint_names()))
    if optical:
        cal = joined_forest(cal, take)
    art = articulation(cal).reordered(take.names).completed(take.rotations, take.positions, take.valid)
    names = art.names
    # The service's one definition of progress, for this one fit (a given tree cannot re-link).
    calibrated = progress_of(cal, default_target(TOLERANCE_M), TOLERANCE_M, tree_fixed=given or cal.known_skeleton)
    standing = {j.joint: j for j in calibrated.joints}
    e = tree_residuals(take.rotations, take.positions, art, take.valid)
    sep = np.linalg.norm(e, axis=-1)
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    joints = [int(j) for j in art.order[1:]]
    row_of = {cal.names[c]: k for k, c in enumerate(cal.joint_child.tolist())}  # a body's joint row in the fit
    titles = [joint_names.get(n, n) for n in names]  # the residual figures' joints, as people name them
    decided = _determined(cal)
    # Bodies ending at a determined joint (a saved skeleton's bones are known whatever this take pinned).
    determined = np.array([cal.known_skeleton or (n in row_of and decided[row_of[n]]) for n in names], dtype=bool)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a joint with no valid frame has no rms: shown as –
        rms = np.sqrt(np.nanmean(sep**2, axis=0))
        worst = np.nanmax(sep, axis=0)
    step(REPORT_STAGES[1])
    slips = _find_slips(take, cal) if slips is None else [_event(x, take.names) for x in slips]
    step(REPORT_STAGES[2])
    duration = float(take.times[-1] - take.times[0]) if take.n_frames > 1 else 0.0
    title = title or f"flockcal calibration report{f' — {source}' if source else ''}"
    made = datetime.now(timezone.utc).isoformat(timespec="seconds")

    parts = [
        "<!doctype html><html lang=en><head><meta charset=utf-8>",
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class=meta>{take.n_frames} frames, {duration:.1f} s at {take.rate_hz:g} Hz, {len(names)} sensors; "
        f"root {html.escape(names[art.root])}; {100 * float(take.valid.mean()):.1f}% of sensor-frames valid; "
        f"made {made}</p>",
        "<h2>Skeleton</h2>",
        _img(skeleton_figure(rec, _pose_frame(take.valid), bvh_world(up), determined), "skeleton drawing"),
        "<h2>Topology</h2>",
        _tree_html(art, {names[j]: rms[j] for j in joints}, standing,
                   cal.humanoid.mapping(cal.names) if cal.humanoid is not None else {}, joint_names),
        "<h2>Humanoid</h2>",
        _humanoid_html(cal),
        "<h2>Calibration progress</h2>",
        _progress_html(calibrated),
    ]
    if optical:
        parts.append(optical_html(cal))
    if cal.loop_candidates:
        parts.append("<p>Loop candidates (non-tree pairs that fit as well as tree joints):</p>")
        parts.append(_table(["<a", "<b", "rms (mm)"], [[Text(cal.names[a]), Text(cal.names[b]), _fmt(r, 1000, 2)]
                                                        for a, b, r in cal.loop_candidates]))

    parts.append("<h2>Bones</h2>")
    # The fit's bones, else (none measured) the articulation's, each named by its own sensor order.
    bones, bone_names = (cal.bones, cal.names) if len(cal.bones) else (bone_arrays(art), art.names)
    bone_rows = [
        [Text(bone_names[body]), Text(str(bone_names[frm] if frm >= 0 else None)), Text(bone_names[to]),
         _fmt(length, 100, 2), _fmt(stderr, 1000, 2)]
        for body, frm, to, length, stderr in zip(bones.body.tolist(), bones.from_joint.tolist(),
                                                 bones.to_joint.tolist(), bones.length.tolist(), bones.stderr.tolist())
    ]  # fmt: skip
    parts.append(_table(["<body", "<from joint", "<to joint", "length (cm)", "std err (mm)"], bone_rows))

    parts.append("<h2>Joints and sensor placement</h2>")
    joint_rows = []
    for j in joints:
        k = row_of.get(names[j])
        joint_rows.append([
            Text(joint_names.get(names[j], "–")), Text(names[j]), Text(names[art.parent[j]]), _fmt(rms[j], 1000, 2),
            _fmt(worst[j], 1000, 2),
            _fmt(_at(cal.epsilon, k), 1000, 4), _fmt(float(np.linalg.norm(art.c[j])), 100, 2),
            _fmt(_at(cal.c_stderr, k), 1000, 2), Text("yes" if k is not None and cal.hinge[k] else "no"),
            Text("yes" if k is not None and decided[k] else "no"), _bars(None if k is None else cal.coverage[k]),
        ])  # fmt: skip
    headers = ["<joint", "<child", "<parent", "rms (mm)", "max (mm)", "ε (mm)", "sensor→joint (cm)",
               "c std err (mm)", "<hinge", "<determined", "<coverage (3 axes)"]  # fmt: skip
    parts.append(_table(headers, joint_rows))
    parts.append(
        "<p class=meta>Coverage: 1 − σ of the mean relative rotation about each principal axis; an empty bar "
        "means that joint was never turned about that axis, so move it more.</p>"
    )

    if joints:
        parts += [
            "<h2>Residuals over time</h2><p class=meta>e = R<sub>child</sub> c + t<sub>child</sub> − "
            "R<sub>parent</sub> l − t<sub>parent</sub>, world axes (paper figs 6–7).</p>",
            _img(residual_time_figure(take.times, e, joints, titles), "residuals over time"),
            "<h2>Residual magnitude histograms</h2><p class=meta>Paper fig 8.</p>",
            _img(residual_histogram_figure(sep, joints, titles), "residual histograms"),
        ]

    parts.append("<h2>Coverage of the data</h2>")
    gaps = _longest_gap_s(take.valid, take.rate_hz)
    cover_rows = [[Text(n), f"{100 * take.valid[:, i].mean():.1f}%", f"{gaps[i]:.2f}"] for i, n in enumerate(names)]
    parts.append(_table(["<sensor", "valid frames", "longest gap (s)"], cover_rows))

    parts.append("<h2>Slip events</h2>")
    if slips:
        slip_rows = [
            [_fmt(s.time_s, 1, 2), Text(s.kind), Text(" ↔ ".join(s.candidates) if s.kind == "swap" else s.sensor),
             Text(", ".join(s.joints)), _fmt(s.jump_mm, 1, 1)]
            for s in slips
        ]  # fmt: skip
        parts.append(_table(["time (s)", "<kind", "<sensor", "<joints", "jump (mm)"], slip_rows))
    else:
        parts.append("<p>None detected.</p>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _humanoid_html(cal: Calibration) -> str:
    """Which humanoid bone each sensor was found on, and the names that say otherwise; or why there is none."""
    from flockcal.solver.calibration_json import NOT_LOOKED_FOR
    from flockcal.solver.humanoid import conflict_message

    hum = cal.humanoid
    if hum is None or not hum.human:
        return f"<p>{html.escape(NOT_LOOKED_FOR if hum is None else hum.reason)}</p>"
    rows = [[Text(sensor), Text(bone)] for sensor, bone in hum.mapping(cal.names).items()]
    out = ("<p>Each body's bone (VRM 1.0 names), found from the tree's shape and the take's motion, whatever "
           "the sensors are called:</p>" + _table(["<sensor", "<found on"], rows))
    if hum.conflicts:
        out += "<p><b>Names that say otherwise</b> (the outputs follow the data):</p><ul>" + "".join(
            f"<li>{html.escape(conflict_message(cal.names, c))}</li>" for c in hum.conflicts) + "</ul>"
    return out


def _progress_html(progress: Progress) -> str:
    """The progress as the kiosk and dashboard show it: the figure, done, and what is missing."""
    head = (f"<p>{progress.joints_done} of {progress.joints_needed} joints calibrated ({progress.percent} %), each "
            f"determined with its centre pinned to {1000 * progress.target_m:.1f} mm: "
            f"<b>{'done' if progress.done else 'not done'}</b>.</p>")
    if not progress.missing:
        return head
    rows = [[Text(m.label), Text(m.joint), Text(m.parent or "–"), Text(m.why or m.state.value)]
            for m in progress.missing_joints()]
    return head + _table(["<joint", "<child", "<parent", "<why not yet"], rows) + \
        "<p class=meta>Same rule as the live service's progress (flockcal's docs/service.md#progress-one-figure-for-the-kiosk-the-dashboard-and-the-api).</p>"


def _determined(cal: Calibration) -> list[bool]:
    """Each joint determined, as the fit's §5 object says (an optical fit: judged from the bodies' poses)."""
    if cal.optical is not None and cal.optical.joint_decisions:
        return [bool(x.get("determined")) for x in cal.optical.joint_decisions]
    return cal.joints.determined.tolist()


def _at(values, k: int | None):
    return None if k is None else values[k]


def _event(x, names):
    """A slip or swap event: itself, or its §5 entry read by the one parser."""
    from flockcal.solver.calibration_json import event_from_json

    return x if hasattr(x, "kind") else event_from_json(x, names)


def write_report(path: str | os.PathLike, calibration, take, **options) -> None:
    """Write the report page to `path` (atomically)."""
    write_atomic(path, report_html(calibration, take, **options))
