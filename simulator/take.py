"""Record a simulated take: a performer's routine sampled at a frame rate, with noise and faults,
returned as a `flockcal.takes.Take` plus the ground truth to compare a fit against.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from flockcal.simulator.body import BodyModel, SimulatorError
from flockcal.simulator.performer import Performer
from flockcal.takes import Take, make_take

FAULT_KEYS = {"dropout", "dropout_burst_s", "slip", "slips", "unit_scale", "hemisphere", "quantise", "orientation", "noise_scale"}


def simulate(
    model: str | BodyModel = "human",
    motion: str = "walk",
    seconds: float = 45.0,
    rate_hz: float = 100.0,
    birds: int | None = 16,
    seed: int = 1,
    noise: str | None = "tracker",
    faults: dict | None = None,
    height: float = 1.75,
    period: float | None = None,
    sta_mm: float | None = None,
) -> tuple[Take, dict]:
    """Simulate a performer wearing tracker sensors: a recorded take and the truth to judge a fit by.

    The same simulated performer as ``flockcal simulate`` and the fake tracker (docs/simulator.md):
    a body model moving through a routine, seen by sensors on the skin, with tracker noise and any
    faults asked for.

    Parameters
    ----------
    model : {"human", "linkage", "pair"} or BodyModel, default "human"
        "human" (2 to 16 sensors), "linkage" (the paper's 6-link chain), "pair" (two sensors 0.565 m
        apart, for the tracker's unit scale), or a body of your own.
    motion : {"walk", "exercise", "kiosk", "idle"}, default "walk"
        The routine (docs/simulator.md, "Motion"); "exercise" moves every joint in turn.
    seconds : float, default 45.0
        Length of the take.
    rate_hz : float, default 100.0
        Frames per second.
    birds : int or None, default 16
        Sensors to keep (the human's first `birds` of its connected order; see docs/simulator.md);
        None keeps every body of the model.
    seed : int, default 1
        Seeds the subject's proportions, the motion and the noise: the same seed gives the same take.
    noise : {"tracker", None}, default "tracker"
        The Flock's measurement noise, or exact poses.
    faults : dict, optional
        Any of ``{"dropout": p, "dropout_burst_s": s, "slips": [{"sensor", "at_time", "distance_m",
        "direction", "angle_deg"}]`` (or one as ``"slip"``), ``"unit_scale": f, "hemisphere": "forward"|…,
        "quantise": 36|72|144, "orientation": "matrix"|"angles"|"quaternion", "noise_scale": f}``.
    height : float, default 1.75
        The human's height, metres.
    period : float, optional
        Seconds one loop of the routine takes (each routine has its own default).
    sta_mm : float, optional
        Soft-tissue artefact: how far a sensor slides over its bone as a joint reaches the end of its
        range. Default 12 mm for the human; 0 turns it off (the linkage and the pair have none).

    Returns
    -------
    take : flockcal.Take
        The recorded frames.
    truth : dict
        The ground truth in the shape of ``flockcal fit --json``: ``root``, ``parent``, ``joints`` (``c``,
        ``l`` in the sensor frames at the take's start), ``bones``; ``slip_events`` lists each slip and
        ``after_slips`` the truth once every slip has happened; ``simulation`` the settings used.

    Raises
    ------
    flockcal.simulator.SimulatorError
        An unknown model, routine or fault, a sensor count the model does not have, or a take of no frames.

    Examples
    --------
    >>> import flockcal
    >>> take, truth = flockcal.simulate(motion="kiosk", seconds=3, birds=6, seed=2)
    >>> take.n_frames, take.names[:3]
    (300, ('pelvis', 'chest', 'head'))
    >>> truth["parent"]["l_forearm"]
    'l_upper_arm'
    >>> slipped, truth = flockcal.simulate(motion="exercise", seconds=3, birds=6,
    ...     faults={"slip": {"sensor": "l_forearm", "at_time": 2.0, "distance_m": 0.02}})
    >>> [e["sensor"] for e in truth["slip_events"]]
    ['l_forearm']
    """
    faults = dict(faults or {})
    perf = performer(model, motion, seconds, rate_hz, birds, seed, noise, faults, height, period, sta_mm)
    return record(perf, 0.0, seconds, motion, noise, faults)


def simulate_session(n_takes: int, model: str | BodyModel = "human", motion: str = "exercise", seconds: float = 45.0,
                     rate_hz: float = 100.0, birds: int | None = 16, seed: int = 1, noise: str | None = "tracker",
                     faults: dict | None = None, height: float = 1.75, period: float | None = None,
                     sta_mm: float | None = None) -> Iterator[tuple[Take, dict]]:
    """One performer's session recorded as `n_takes` takes of `seconds` each, back to back: (take, truth)
    for each in turn, made as asked for (a session is many takes, none of them kept).

    The same performer throughout (the subject, the sensors and their straps from `seed`), moving through
    one performance of `motion` that the takes cut into pieces: take k holds seconds k·`seconds` to
    (k+1)·`seconds` of it, its times from 0. The exercise routine is planned to loop once over the whole
    session, so each take turns its own share of the joints. Faults are the performance's: a slip at
    `at_time` (seconds into the session) moves its sensor for that take and every later one. Each truth is
    `simulate`'s, at its take's start, with `simulation["take"]` (1-based), `["takes"]` and `["start_s"]`.
    """
    if n_takes < 1:
        raise SimulatorError(f"a session needs at least one take, not {n_takes}")
    faults = dict(faults or {})
    total = n_takes * float(seconds)
    perf = performer(model, motion, total, rate_hz, birds, seed, noise, faults, height, period, sta_mm)
    for k in range(n_takes):
        take, truth = record(perf, k * float(seconds), seconds, motion, noise, faults)
        truth["simulation"].update(take=k + 1, takes=n_takes, start_s=k * float(seconds))
        yield take, truth


def performer(model, motion: str, seconds: float, rate_hz: float, birds, seed: int, noise, faults: dict,
              height: float, period, sta_mm) -> Performer:
    """The `Performer` `simulate` records: `seconds` is what the routine is planned for, `faults` as there."""
    unknown = set(faults) - FAULT_KEYS
    if unknown:
        raise SimulatorError(f"unknown fault(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(FAULT_KEYS))}")
    if isinstance(model, str) and model != "human" and birds == 16:
        birds = None  # the default 16 is for the human suit; the rigs have their own counts
    perf = Performer(
        model, routine=motion, seed=seed, noise=noise, rate_hz=rate_hz, birds=birds,
        period=period, height=height, seconds=seconds, sta_mm=sta_mm,
    )  # fmt: skip
    if "noise_scale" in faults:
        perf.set_noise(noise, float(faults["noise_scale"]))
    if faults.get("dropout"):
        perf.set_dropout(float(faults["dropout"]), float(faults.get("dropout_burst_s", 0.0)))
    if "unit_scale" in faults:
        perf.set_unit_scale(float(faults["unit_scale"]))
    if faults.get("hemisphere"):
        perf.set_hemisphere(faults["hemisphere"])
    if faults.get("quantise"):
        perf.set_quantise(float(faults["quantise"]), faults.get("orientation", "matrix"))
    slips = list(faults.get("slips", []))
    if "slip" in faults:
        slips.append(faults["slip"])
    for s in slips:
        if not isinstance(s, dict) or "sensor" not in s or "distance_m" not in s:
            raise SimulatorError("each slip needs at least {'sensor': name, 'distance_m': metres, 'at_time': seconds}")
        perf.inject_slip(
            s["sensor"], float(s["distance_m"]), at_time=float(s.get("at_time", seconds / 2)),
            direction=s.get("direction"), angle_deg=float(s.get("angle_deg", 0.0)),
        )  # fmt: skip
    return perf


def record(perf: Performer, start_s: float, seconds: float, motion: str, noise, faults: dict) -> tuple[Take, dict]:
    """(take, truth) of `perf` from `start_s` for `seconds`, the take's times from 0 (`motion`, `noise`,
    `faults`: what it was made with, for the truth)."""
    rate_hz = perf.rate_hz
    n = int(round(seconds * rate_hz))
    if n < 1:
        raise SimulatorError(f"{seconds} s at {rate_hz:g} Hz gives no frames")
    times = np.arange(n) / float(rate_hz)
    R, p, valid = perf.poses(start_s + times)
    take = make_take(R, p, perf.names, rate_hz, valid=valid, times=times, source="simulated take")

    truth = perf.truth(at_time=float(start_s))
    if perf.sta is not None:
        # How far the skin actually carried each sensor in this take: the figure to judge a fit by.
        # Every 8th frame is plenty for the rms and the peak of a motion this smooth, at an eighth of the cost.
        moved = perf.soft_tissue(start_s + times[::8])
        truth["soft_tissue"]["rms_mm"] = {nm: round(float(x), 3) for nm, x in zip(perf.names, 1000 * np.sqrt((moved**2).mean(axis=0)))}
        truth["soft_tissue"]["max_mm"] = {nm: round(float(x), 3) for nm, x in zip(perf.names, 1000 * moved.max(axis=0))}
    if truth["slip_events"]:
        after = perf.truth()
        truth["after_slips"] = {"joints": after["joints"], "bones": after["bones"]}
    truth["simulation"] = {
        "model": perf.model.kind,
        "motion": motion,
        "seconds": float(seconds),
        "rate_hz": float(rate_hz),
        "frames": n,
        "seed": perf.seed,
        "noise": noise,
        "sta_mm": perf.sta_mm,
        "faults": {k: v for k, v in faults.items() if k not in ("slip", "slips")},
    }
    return take, truth
