"""Pydantic models of the REST API: requests are strict, responses mirror design.md §5.

Only this module and the routes use pydantic; everything below them passes typed objects (a `Calibration`,
a `store.SessionRow`, an `events.Event`, a `Progress`), which a route answers with: FastAPI validates it into
the route's model once (a dataclass by its attributes; a fit by its §5 object, solver/calibration_json.py).
Result models allow extra fields so the §5 contract can grow without breaking the API.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from flockcal.server.openapi import preset_or_none, sensor_enum, sensor_or_none
from flockcal.server.settings import PERFORMER_PATTERN, performer_pattern
from flockcal.simulator.motion import ROUTINES
from flockcal.solver.progress import STATES

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 _.\-]{0,63}$"
Name = str  # validated against NAME_PATTERN where it enters


class Strict(BaseModel):
    # strict: a number sent as a string ("0.01") or a boolean is a 422, never converted (an int is a number).
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True, strict=True)


class Open(BaseModel):
    model_config = ConfigDict(extra="allow")


# --- §5 result -----------------------------------------------------------------------------------
class Joint(Open):
    child: str
    parent: str
    c: list[float | None]
    l: list[float | None]
    rms_m: float | None = None
    epsilon: float | None = None
    singular_values: list[float | None] = []
    hinge: bool = False
    axis_child: list[float | None] | None = None
    axis_parent: list[float | None] | None = None
    coverage: list[float | None] = []
    c_stderr_m: float | None = None
    l_stderr_m: float | None = None
    name: str | None = Field(None, description="the joint as people name it: the humanoid's on a human tree "
                                               "('left knee', 'lower back'), else read from the sensor names")


class NameConflict(Open):
    sensor: str
    named: str = Field(description="the humanoid bone (VRM 1.0 name) the sensor's name implies")
    found: str = Field(description="the bone the data found the sensor on (the outputs follow this)")
    message: str


class Bone(Open):
    body: str
    from_joint: str | None = None
    to_joint: str
    length_m: float | None = None
    stderr_m: float | None = None


class LoopCandidate(Open):
    a: str
    b: str
    rms_m: float | None = None


class SlipEvent(Open):
    time_s: float
    sensor: str
    candidates: list[str] = []
    joints: list[str] = []
    jump_mm: float | None = None
    # A session's result lists its slips (swaps are events of their own): the §5 entry's kind goes unsaid.
    kind: Literal["slip", "swap"] = Field("slip", exclude=True)


class CalibrationResult(Open):
    """Exactly what `flockcal fit --json` prints (design.md §5)."""

    sensors: list[str]
    root: str | None = None
    parent: dict[str, str] = {}
    frames: int = 0
    joints: list[Joint] = []
    bones: list[Bone] = []
    loop_candidates: list[LoopCandidate] = []
    slip_events: list[SlipEvent] = []
    humanoid: dict[str, str] | None = Field(
        None, description="{sensor: VRM 1.0 bone} found from the tree and the motion; null when the tree is not "
                          "human-shaped (`humanoid_note` says why) or no humanoid was looked for")
    humanoid_conflicts: list[NameConflict] = Field(
        [], description="sensors whose names say another bone than the one found (docs/solver.md)")


# --- sessions ------------------------------------------------------------------------------------
class SessionCreate(Strict):
    # Documented as the API applies it, to the name stripped of surrounding white space (openapi.py).
    performer: str = Field(min_length=1, max_length=64, pattern=PERFORMER_PATTERN,
                           description="who is wearing the sensors (1–64 characters, no slashes, quotes or < >)",
                           json_schema_extra={"pattern": performer_pattern()})
    hierarchy: dict[str, str] | None = Field(
        None, description="known {child: parent} map, root omitted; leave out for automatic topology")
    # The service's own sensors and presets, listed in its document (server/openapi.py).
    root: str | None = Field(None, pattern=NAME_PATTERN, description="root body; default chosen by the solver",
                             json_schema_extra=sensor_or_none)
    skeleton: str | None = Field(
        None, pattern=NAME_PATTERN, json_schema_extra=preset_or_none,
        description="named preset instead of `hierarchy` (GET /api/sessions/presets): 'auto' (default), 'human' "
                    "(the simulator's body) or a saved skeleton (its tree and bones kept, only placements fitted)")
    profile: Literal["stage", "kiosk"] | None = Field(
        None, description="how the session decides it is calibrated: 'stage' (joints pinned to the service's "
                          "--target-mm) or 'kiosk' (pinned to 10 mm and no longer changed by more data: what a "
                          "guest's avatar needs); default: the service's --profile (docs/service.md, Progress)")
    lease_s: float | None = Field(
        None, ge=1.0, le=3600.0, allow_inf_nan=False,
        description="end the session this many seconds after its client last renewed it (POST "
                    "/api/sessions/{id}/lease): a kiosk page that goes away does not leave it live; default: no lease")


class SessionSummary(Open):
    id: str
    performer: str
    state: Literal["live", "stopped", "interrupted"]
    frames: int = 0
    started_at: float | None = None
    time_s: float | None = None
    hierarchy: dict[str, str] | None = None
    root: str | None = None
    fit_error: str | None = None


class Session(Open):
    id: str
    performer: str
    state: Literal["live", "stopped", "interrupted"]
    root: str | None = None
    hierarchy: dict[str, str] | None = None
    names: list[str]
    device: str
    rate_hz: float | None = None
    created_at: float = Field(description="unix s when it started: the service clock's stamp, which never steps "
                                          "back (docs/service.md#clock)")
    stopped_at: float | None = Field(None, description="created_at + duration_s: never before created_at")
    duration_s: float | None = Field(None, description="how long it recorded (so far, while live), measured on the "
                                                       "monotonic clock: a step of the wall clock does not move it")
    frames: int = 0
    recording: str | None = None
    note: str | None = None
    has_result: bool = False
    has_recording: bool = False
    has_raw_recording: bool = False
    skeleton: str | None = Field(None, description="the saved skeleton the session was started with, if any")
    profile: str | None = Field(None, description="'stage' or 'kiosk': how the session decides it is calibrated")
    lease_s: float | None = Field(None, description="a live session's lease (it ends this long after its client "
                                                    "last renewed it); null: none")
    progress: float | None = Field(None, description="calibration progress 0..1 (GET /api/sessions/{id}/progress)")
    done: bool | None = Field(None, description="every joint calibrated (null: not known for this session)")
    pinned: bool = Field(False, description="kept whole by retention (POST /api/sessions/{id}/pin)")
    pruned_at: float | None = Field(None, description="when retention removed its frames and raw recording "
                                                      "(unix s; /take and /raw then answer 410)")
    pruned_reason: str | None = None


class SessionList(BaseModel):
    sessions: list[Session]
    live: str | None = Field(None, description="id of the live session, if any")


class MissingJoint(Open):
    joint: str = Field(description="the joint, named by its child body (= the sensor it belongs to)")
    parent: str | None = None
    label: str = Field(description="the joint as people name it ('left elbow')")
    state: Literal[STATES] = Field(description="how far it is from calibrated (docs/service.md#progress-one-figure-for-the-kiosk-the-dashboard-and-the-api)")
    why: str | None = Field(None, description="why it is not calibrated yet, in plain words")
    undone: dict | None = Field(None, description="{reason: slip | loss | tree, time_s, sensor}: it was calibrated "
                                                  "once and this undid it")


class JointProgress(MissingJoint):
    progress: float
    done: bool
    error_m: float | None = Field(None, description="the centre's error along the worst direction it needs")


class Hint(Open):
    joint: str
    label: str
    progress: float
    hint: str


class Lease(Open):
    session_id: str
    lease_s: float = Field(description="the lease's length, seconds")
    expires_in_s: float = Field(description="seconds until the session ends unless renewed again")


class Progress(Open):
    """One definition of calibration progress (docs/service.md#progress-one-figure-for-the-kiosk-the-dashboard-and-the-api): what the kiosk ring and the dashboard
    show."""

    session_id: str
    live: bool = Field(description="the live session (figures move on), or a stopped one (as it ended)")
    time_s: float | None = Field(None, description="session clock of the newest fit (live sessions)")
    fit_seq: int | None = Field(None, description="the fit this belongs to: the same as the websocket's fit message")
    frames: int = 0
    state: Literal["no_fit", "calibrating", "done"]
    progress: float = Field(description="0..1: every sensor but the root counts; 1 only when done")
    percent: int = Field(description="progress as whole percent, rounded down: what the kiosk ring shows")
    done: bool = Field(description="every sensor but the root has its joint determined to the target")
    done_at_s: float | None = Field(None, description="session time at which it became done")
    target_m: float = Field(description="the joint-centre error counted as calibrated (serve --target-mm)")
    joints_done: int
    joints_needed: int
    missing: list[MissingJoint] = Field(description="the joints not calibrated yet, the one furthest from it first")
    joint_progress: list[JointProgress] = Field(description="every sensor but the root, in the tree's order")
    hints: list[Hint] = []
    note: str | None = None
    profile: str | None = Field(None, description="'stage' or 'kiosk': the rule `done` follows (`rule`)")
    rule: str | None = Field(None, description="that rule in plain words, for a help text")
    stalled_s: float | None = Field(None, description="session seconds over which the figure gained less than "
                                                      "10 points, once that is 8 s or more (a guest who stopped "
                                                      "moving); else null")
    prompt: str | None = Field(None, description="a patient prompt while stalled: the joint to move and how")


class Status(Open):
    connected: bool
    birds: int | None = None
    rate_hz: float | None = None
    frames: int = 0
    dropped_records: int = 0
    resynced: int = 0
    reconnects: int = 0
    last_error: str | None = None
    device: str | None = None
    sensors: list[str] = []
    session: SessionSummary | None = None
    simulator: bool = False
    retention: dict | None = Field(None, description="serve --keep-days/--keep-disk, the data directory's size, "
                                                     "sessions pruned and pinned (server/retention.py)")
    process: dict | None = Field(None, description="the service's memory: rss_mb, python_blocks (Python's live "
                                                   "allocations), threads (server/memory.py)")
    disk: dict | None = Field(None, description="the data directory's disk: full (no room to record: below "
                                               "--min-free-mb, or a write failed), free_bytes, reserve_bytes, "
                                               "since, message (server/limits.py)")
    connections: dict | None = Field(None, description="cap, request_deadline_s, http_open and the connections "
                                                       "timed_out, evicted and shed (server/connections.py)")
    downloads: dict | None = Field(None, description="download slots: limit, running (held now), stall_s and "
                                                     "stalled (downloads cut off for a client that took no data; "
                                                     "server/downloads.py)")
    outputs: dict | None = Field(None, description="the live humanoid streams, null when none was asked for: vrpn "
                                                   "(port, clients with address, state and channel, reports, "
                                                   "dropped), vmc (targets, rate_hz, bundles_sent, failed, "
                                                   "last_error), humanoid (streaming, reason, bones) and problems "
                                                   "(outputs that could not start; server/outputs.py)")
    clock: dict | None = Field(None, description="the service clock: service_s (the time retention ages count "
                                                 "in), offset_s (the wall clock's steps, summed), stamp_ahead_s "
                                                 "(stamps ahead of a wall clock that stepped back), steps and "
                                                 "last_step (server/clock.py)")


class ResidualSeries(BaseModel):
    session_id: str
    joint: str | None = None
    times: list[float] = Field(description="session clock, seconds")
    joints: dict[str, list[float | None]] = Field(description="{joint child name: rms in mm per time}")
    more: bool = Field(False, description="later samples exist: ask again with since=next_since")
    next_since: float | None = Field(None, description="the `since` of the next page (the last time here)")


class Event(Open):
    id: int
    type: str = Field(description="slip | tracker | session")
    session_id: str | None = None
    time_s: float | None = Field(None, description="session clock, seconds")
    wall_time: float


class EventList(BaseModel):
    session_id: str
    events: list[Event]
    more: bool = Field(False, description="later events exist: ask again with since=next_since")
    next_since: int | None = Field(None, description="the `since` of the next page (the last id here)")


class SlipRequest(Strict):
    sensor: str = Field(pattern=NAME_PATTERN, json_schema_extra=sensor_enum)
    distance_m: float = Field(0.02, gt=0, le=0.5, description="how far the sensor slides on the skin, metres "
                                                               "(default 0.02: the 2 cm slip of design.md §6)")
    at_routine_s: float | None = Field(None, ge=0, le=86400, description="when, on the simulated performer's own clock "
                                       "(seconds since it began its routine: GET /api/simulator's clock_s), the "
                                       "sensor slides; a moment not streamed yet (409 otherwise). Default: the next "
                                       "frame. A slip scheduled here lands on the same moment of the routine "
                                       "whatever the machine's load")


class MotionRequest(Strict):
    # The routines are documented, not validated here: an unknown one is a 400 that names the routines.
    routine: str = Field(pattern=r"^[a-z_]{1,32}$", description="exercise | walk | kiosk | idle",
                         json_schema_extra={"enum": list(ROUTINES)})


class SimulatorReply(Open):
    ok: bool = True
    message: str


class SlipReply(SimulatorReply):
    sensor: str
    distance_m: float
    session_id: str | None = Field(None, description="the live session the slip happens in, if any")
    at_s: float | None = Field(None, description="the slip's sample time: the session time (s) of the first frame "
                                                 "in which the sensor sits at its new place; null without a live "
                                                 "session that has frames")
    in_s: float | None = Field(None, description="seconds from the reply until that sample is measured (the simulator "
                                                 "computes poses up to 0.1 s ahead; negative if already measured)")
    routine_s: float = Field(description="the slip's moment on the simulated performer's clock (seconds since it "
                                         "began its routine)")


class SimulatorState(Open):
    routine: str = Field(description="the routine the simulated performer does: exercise | walk | kiosk | idle")
    period_s: float = Field(description="the routine's loop length: clock_s modulo this is the moment of the loop")
    clock_s: float = Field(description="the performer's clock: seconds since it began its routine, up to the last "
                                       "pose computed (the simulator computes poses up to 0.1 s ahead)")
    seed: int
    sta_mm: float = Field(description="soft-tissue artefact: the largest slide of a skin sensor, mm (0: rigid)")
    slips: list[dict] = Field(description="slips injected so far, on the performer's clock: {time_s, sensor, jump_mm, "
                                          "angle_deg, displacement_bone_m}")


class ClientMessage(BaseModel):
    """A websocket client's message (docs/service.md#websocket-wslive) read off its JSON object once: the
    fields the service acts on, each as sent (a missing one as its default). What each must be, and the
    message that says so, is the route's (server/routes/live.py)."""

    model_config = ConfigDict(extra="allow")

    type: Any = None  # "subscribe" | "ping"
    token: Any = None
    rate_hz: Any = 10  # messages a second; null: the publish rate
    content: Any = ["status"]


class ErrorReply(BaseModel):
    detail: str = Field(description="what went wrong and what to do about it")
    error: str = Field(description="machine-readable code")
