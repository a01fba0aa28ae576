"""The live humanoid streams (issue 47, items 4 and 5) against the real service: uvicorn on loopback, the
built-in simulator's performer, a session recorded and stopped (its final fit then drives the streams).

VRPN: VRPN's own client (`vrpn_print_devices`, built from VRPN's sources; ../shared/tools/vrpn from the
repository's root) over the UDP channel it asks for and over TCP alone, and a client this file writes from
VRPN's Format_Of_Protocol.txt (TCP, big-endian, 8-byte padding) for the exact numbers and a client that stops
reading. VMC: python-osc's UDP server as the receiver. Bad outputs (a VRPN port in use, VMC hosts and ports
that cannot be used) against `flockcal serve` itself.

Oracles: the stopped session's stored result (its joint centres), and this file's own table of which
simulator body is which humanoid bone.
"""

from __future__ import annotations

import collections
import re
import signal
import socket
import struct
import subprocess
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_server import BlockingOSCUDPServer

from flockcal.clock import SYSTEM
from flockcal.server.settings import Settings
from server_helpers import ServerProcess, ServerThread, free_port, wait_connected
from service_process import wait_for

VRPN_TOOLS = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "vrpn"
PRINT_DEVICES = VRPN_TOOLS / "vrpn_print_devices"

BODY_OF = ["pelvis", "abdomen", "chest", "head", "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm",
           "r_forearm", "r_hand", "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot"]
UNITY = ["Hips", "Spine", "Chest", "Head", "LeftUpperArm", "LeftLowerArm", "LeftHand", "RightUpperArm",
         "RightLowerArm", "RightHand", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "RightUpperLeg",
         "RightLowerLeg", "RightFoot"]
TREE = {"abdomen": "pelvis", "chest": "abdomen", "head": "chest", "l_upper_arm": "chest", "l_forearm": "l_upper_arm",
        "l_hand": "l_forearm", "r_upper_arm": "chest", "r_forearm": "r_upper_arm", "r_hand": "r_forearm",
        "l_thigh": "pelvis", "l_shin": "l_thigh", "l_foot": "l_shin", "r_thigh": "pelvis", "r_shin": "r_thigh",
        "r_foot": "r_shin"}
PARENT_BONE = {1: 0, 2: 1, 3: 2, 4: 2, 5: 4, 6: 5, 7: 2, 8: 7, 9: 8, 10: 0, 11: 10, 12: 11, 13: 0, 14: 13, 15: 14}
CLAIM_M = 1e-6  # docs/outputs.md: a bone and its parent bone are the fitted bone apart to a micrometre
# vrpn_print_devices prints metres with 2 decimals: each coordinate of a difference is off by up to 0.01.
PRINTED_M = 0.01 * 3 ** 0.5
RATE_HZ = 60


def expected_gaps(result: dict) -> dict[int, float]:
    """{bone k: distance from its parent bone's start}: the parent body's two joint centres (its inboard one
    and the child's), from the hips' centre (the midpoint of the hip joints) for bodies on the hips."""
    at = {j["child"]: (np.array(j["c"]), np.array(j["l"])) for j in result["joints"]}
    assert result["root"] == "pelvis"
    hips = (at["l_thigh"][1] + at["r_thigh"][1]) / 2
    out = {}
    for k, p in PARENT_BONE.items():
        start = hips if p == 0 else at[BODY_OF[p]][0]
        out[k] = float(np.linalg.norm(at[BODY_OF[k]][1] - start))
    return out


class Receiver:
    """python-osc's UDP server on a free loopback port, keeping what arrives (address, args, arrival time)."""

    def __init__(self):
        self.got: collections.deque = collections.deque(maxlen=50000)
        d = Dispatcher()
        d.set_default_handler(lambda address, *args: self.got.append((address, args, time.monotonic())))
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), d)  # one datagram at a time: bundles stay whole
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def bundles(self, since: float = 0.0) -> list[dict]:
        """What arrived since `since`, one dict per bundle: {address or bone name: args}, from each
        /VMC/Ext/OK on (the first message of every bundle)."""
        out = []
        for address, args, at in list(self.got):
            if at < since:
                continue
            if address == "/VMC/Ext/OK":
                out.append({"at": at})
            if out:
                out[-1][args[0] if address == "/VMC/Ext/Bone/Pos" else address] = args
        return out[:-1]  # the last may still be arriving

    def wait(self, condition, timeout: float = 60.0, since: float = 0.0) -> list[dict]:
        """The bundles since `since` once `condition` holds of them (`timeout` only stops a hung test)."""
        return settled(lambda: self.bundles(since), condition, timeout)

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def outputs(url: str) -> dict:
    return httpx.get(url + "/api/status", timeout=10).json()["outputs"]


def settled(what, condition, timeout: float = 60.0):
    """`what()` once `condition` holds of it (`timeout` only stops a hung test)."""
    seen = []

    def met() -> bool:
        seen[:] = [what()]
        return condition(seen[0])

    wait_for(met, timeout, lambda: f"condition met (last: {seen[0] if seen else None})", every=0.1)
    return seen[0]


@pytest.fixture(scope="module")
def streams(tmp_path_factory):
    receiver = Receiver()
    nobody = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a port no receiver listens on
    nobody.bind(("127.0.0.1", 0))
    absent = nobody.getsockname()[1]
    nobody.close()
    settings = Settings(device=f"sim://streams?birds=16&motion=exercise&rate={RATE_HZ}&baud=921600", birds=16,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("streams"), vrpn_port=0,
                        osc_targets=(f"127.0.0.1:{receiver.port}", f"127.0.0.1:{absent}"))
    try:
        with ServerThread(settings) as srv:
            wait_connected(srv.url)
            port = srv.service.outputs.vrpn.port
            before = receiver.wait(lambda b: len(b) >= 10)  # no session, no fit: nothing to stream yet
            r = httpx.post(srv.url + "/api/sessions", json={"performer": "Vee", "hierarchy": TREE, "root": "pelvis"})
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            settled(lambda: outputs(srv.url)["humanoid"], lambda h: h["streaming"])
            live = receiver.wait(lambda b: len(b) >= 5 and "Hips" in b[-1], since=time.monotonic())
            settled(lambda: httpx.get(srv.url + "/api/status").json()["session"]["frames"], lambda n: n >= 4 * RATE_HZ)
            assert httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=60).status_code == 200
            result = httpx.get(srv.url + f"/api/sessions/{sid}/result", timeout=30).json()
            stopped = time.monotonic()
            receiver.wait(lambda b: len(b) >= 3 and b[-1]["/VMC/Ext/OK"][1] == 3, since=stopped)
            yield {"srv": srv, "port": port, "result": result, "receiver": receiver, "before": before, "live": live,
                   "stopped": stopped, "absent": absent}
    finally:
        receiver.close()


# -- VRPN -------------------------------------------------------------------------------------------------
def print_devices(device: str, frames: int = 30, seconds: float = 0.0,
                  timeout: float = 60.0) -> tuple[list[np.ndarray], str]:
    """vrpn_print_devices on `device` until it has printed `frames` whole frames (sensors 0-15 in a row) and
    run `seconds`: [(16, 3) positions], and what else it printed. The client is stopped and reaped either way."""
    if not PRINT_DEVICES.exists():
        pytest.skip(f"VRPN's client is not at {PRINT_DEVICES} (../shared/tools/vrpn beside the repository)")
    proc = subprocess.Popen([str(PRINT_DEVICES), device], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    pattern = re.compile(r"Tracker (\S+), sensor (\d+):\s*\n\s*pos \(\s*([-\d.]+),\s*([-\d.]+),\s*([-\d.]+)\)")
    try:
        started = time.monotonic()
        # `seconds` is real time on purpose: the client's own ping timer (3 s) is what is watched.
        wait_for(lambda: proc.poll() is not None or (
            len(whole_frames(pattern.findall("".join(lines[:len(lines) - 1])), device)) >= frames
            and time.monotonic() - started >= seconds), timeout, f"{frames} frames printed by {device}")
    finally:
        proc.send_signal(signal.SIGINT)  # its Ctrl-C handler ends the loop and flushes what it printed
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
        reader.join(10)
    text = "".join(lines)
    return whole_frames(pattern.findall(text), device), text


def whole_frames(reports, device: str) -> list[np.ndarray]:
    frames, run = [], []
    for name, sensor, *xyz in reports:
        assert name == device
        if int(sensor) != len(run):
            run = []
        if int(sensor) == len(run):
            run.append([float(v) for v in xyz])
        if len(run) == 16:
            frames.append(np.array(run))
            run = []
    return frames


@pytest.mark.parametrize("channel", ["udp", "tcp"])
def test_vrpns_own_client_gets_every_bone_a_fitted_bone_apart(streams, channel):
    """`vrpn_print_devices flockcal@127.0.0.1:PORT` (its UDP channel) and `flockcal@tcp://…` (TCP only): every
    sensor 0-15 reported, frame after frame, each bone its parent bone's fitted bone away (to print precision)."""
    port = streams["port"]
    device = f"flockcal@127.0.0.1:{port}" if channel == "udp" else f"flockcal@tcp://127.0.0.1:{port}"
    # Over UDP it runs 4 s: a client that hears no answer to its ping warns after 3 s.
    frames, text = print_devices(device, seconds=4.0 if channel == "udp" else 0.0)
    assert len(frames) >= 30, text[-2000:]
    assert "No response from server" not in text  # the server answers the client's pings
    gaps = expected_gaps(streams["result"])
    for f in frames:
        for k, p in PARENT_BONE.items():
            assert abs(np.linalg.norm(f[k] - f[p]) - gaps[k]) <= PRINTED_M, (BODY_OF[k], f[k], f[p], gaps[k])


class RawVrpn:
    """A TCP-only VRPN client written from VRPN's Format_Of_Protocol.txt: a 24-byte cookie each way, then
    messages of a 24-byte header (length of header + payload, seconds, microseconds, sender, type; 32-bit
    big-endian; the sixth word is padding) and a payload padded to 8 bytes. Negative types are the
    connection's own: -1 a sender's name, -2 a type's name."""

    def __init__(self, port: int, rcvbuf: int | None = None):
        self.sock = socket.socket()
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(30)
        self.sock.connect(("127.0.0.1", port))
        self.sock.sendall(b"vrpn: ver. 07.35  0".ljust(24, b"\0"))  # another minor version: still 07
        self.buf = b""
        self.cookie = self.take(24)
        self.senders: dict[int, str] = {}
        self.types: dict[int, str] = {}

    def take(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def message(self) -> tuple[str, str, float, bytes]:
        """(type name, sender name, time, payload) of the next message; names of descriptions are kept."""
        length, sec, usec, sender, kind = struct.unpack(">IIIii", self.take(24)[:20])
        size = length - 24
        payload = self.take(size + (-size) % 8)[:size]
        if kind in (-1, -2):
            n = struct.unpack(">i", payload[:4])[0]
            (self.senders if kind == -1 else self.types)[sender] = payload[4:4 + n - 1].decode()
        return self.types.get(kind, str(kind)), self.senders.get(sender, str(sender)), sec + usec / 1e6, payload

    def send(self, kind: int, sender: int, payload: bytes = b"") -> None:
        now = time.time()
        head = struct.pack(">IIIiiI", 24 + len(payload), int(now), int(now % 1 * 1e6), sender, kind, 0)
        self.sock.sendall(head + payload + b"\0" * ((-len(payload)) % 8))

    def describe(self, kind: int, number: int, name: str) -> None:
        raw = name.encode() + b"\0"
        self.send(kind, number, struct.pack(">i", len(raw)) + raw)

    def close(self):
        self.sock.close()


def test_a_client_written_from_the_protocol_reads_the_exact_segments(streams):
    """Over TCP: the server's cookie, its sender `flockcal` and the Pos_Quat type described, then 64-byte
    Pos_Quat payloads (sensor, sensor again, position and quaternion x y z w as doubles) stamped with the
    frame's wall time; consecutive bones the fitted bone apart to the documented micrometre, unit
    quaternions; a ping answered with a pong, a request for the tracker-to-room transform answered."""
    client = RawVrpn(streams["port"])
    try:
        assert client.cookie.startswith(b"vrpn: ver. 07.") and client.cookie[18:19] == b"0"
        client.describe(-1, 0, "flockcal")  # the client's own numbering of names
        client.describe(-2, 0, "vrpn_Base ping_message")
        client.describe(-2, 1, "vrpn_Tracker Request_Tracker_To_Room")
        client.send(0, 0)
        client.send(1, 0)
        frames, pending, answers = [], {}, set()
        deadline = time.monotonic() + 60  # only stops a hung test
        while (len(frames) < 20 or answers != {"vrpn_Base pong_message", "vrpn_Tracker To_Room"}) \
                and time.monotonic() < deadline:
            kind, sender, when, payload = client.message()
            if kind in ("vrpn_Base pong_message", "vrpn_Tracker To_Room"):
                assert sender == "flockcal"
                answers.add(kind)
                if kind == "vrpn_Tracker To_Room":
                    assert struct.unpack(">7d", payload) == (0, 0, 0, 0, 0, 0, 1)
            if kind != "vrpn_Tracker Pos_Quat":
                continue
            assert sender == "flockcal" and len(payload) == 64
            sensor, again, *numbers = struct.unpack(">ii7d", payload)
            assert sensor == again and 0 <= sensor < 16
            assert abs(when - time.time()) < 5  # the frame's own time, on the wall clock
            assert np.linalg.norm(numbers[3:]) == pytest.approx(1, abs=1e-12)
            pending[sensor] = (when, np.array(numbers[:3]))
            if len(pending) == 16 and len({w for w, _ in pending.values()}) == 1:
                frames.append(np.array([pending[k][1] for k in range(16)]))
                pending = {}
        assert answers == {"vrpn_Base pong_message", "vrpn_Tracker To_Room"}
        assert len(frames) >= 20
        gaps = expected_gaps(streams["result"])
        for f in frames:
            for k, p in PARENT_BONE.items():
                assert abs(np.linalg.norm(f[k] - f[p]) - gaps[k]) <= CLAIM_M, BODY_OF[k]
    finally:
        client.close()


def test_the_status_lists_each_vrpn_client_and_a_client_that_stops_reading_is_dropped(streams):
    """A TCP client with a small receive buffer that reads nothing after its cookie is dropped once its
    backlog fills (about a second of reports); the status listed it meanwhile, and a client after it is
    served as before."""
    url = streams["srv"].url
    dropped = outputs(url)["vrpn"]["dropped"]["slow"]
    stalled = RawVrpn(streams["port"], rcvbuf=4096)
    try:
        mine = f"127.0.0.1:{stalled.sock.getsockname()[1]}"
        listed = settled(lambda: outputs(url)["vrpn"], lambda v: any(c["address"] == mine for c in v["clients"]))
        assert [c for c in listed["clients"] if c["address"] == mine][0]["channel"] == "tcp"
        after = settled(lambda: outputs(url)["vrpn"], lambda v: v["dropped"]["slow"] > dropped, timeout=120)
        assert all(c["address"] != mine for c in after["clients"])
    finally:
        stalled.close()
    fresh = RawVrpn(streams["port"])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and fresh.message()[0] != "vrpn_Tracker Pos_Quat":
            pass
    finally:
        fresh.close()
    assert httpx.get(url + "/api/status").json()["connected"]


# -- VMC --------------------------------------------------------------------------------------------------
def test_vmc_every_bone_arrives_with_its_fitted_bone_as_local_position(streams):
    """Each bundle after the stop: /VMC/Ext/OK (loaded, calibrated), /VMC/Ext/T, /VMC/Ext/Root/Pos "root" at
    the origin unturned, and all 16 bones by their Unity names, each with 7 numbers (position, unit
    quaternion); a bone's local position is its parent bone's fitted bone (to the documented micrometre)."""
    got = streams["receiver"].wait(lambda b: len(b) >= 30, since=streams["stopped"])
    gaps = expected_gaps(streams["result"])
    # Tracking is OK while frames younger than 0.25 s come with every bone's sensor valid: a starved
    # machine may hold the reader up now and then, so it must be said, not always.
    assert any(b["/VMC/Ext/OK"][3] == 1 for b in got[-30:])
    for bundle in got[-30:]:
        assert bundle["/VMC/Ext/OK"][:3] == (1, 3, 0)
        assert bundle["/VMC/Ext/Root/Pos"] == ("root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        assert set(UNITY) <= set(bundle)
        for k, name in enumerate(UNITY):
            args = bundle[name]
            assert len(args) == 8 and args[0] == name
            assert np.linalg.norm(args[4:]) == pytest.approx(1, abs=1e-6)
            if k in PARENT_BONE:
                assert np.linalg.norm(args[1:4]) == pytest.approx(gaps[k], abs=CLAIM_M), name


def test_vmc_says_the_calibration_state_and_its_time_at_the_stated_rate(streams):
    """Before any session: not loaded, uncalibrated, no bones. While the session calibrates: loaded,
    calibrating (2) or already calibrated (3). After the stop: calibrated. /VMC/Ext/T is the sender's
    clock: its steps are ticks of 1/60 s (the default rate), with a second receiver named that is not
    there."""
    assert all(b["/VMC/Ext/OK"][:2] == (0, 0) and "Hips" not in b for b in streams["before"])
    live = [b for b in streams["live"] if "Hips" in b]
    assert live and all(b["/VMC/Ext/OK"][:2] in ((1, 2), (1, 3)) for b in live)
    got = streams["receiver"].wait(lambda b: len(b) >= 60, since=streams["stopped"])
    # /VMC/Ext/T is the bundle's tick on the sender's 1/60 s grid: a sender held up by a loaded machine skips
    # ticks (never sends two at once), so every step is a whole number of ticks, and most are one.
    ticks = np.diff([b["/VMC/Ext/T"][0] for b in got]) * 60
    assert np.all(ticks >= 1 - 1e-3) and np.abs(ticks - np.round(ticks)).max() < 1e-2, ticks
    assert np.median(np.round(ticks)) == 1, ticks
    # The second receiver named was never there: fire-and-forget, it costs the first one nothing.
    vmc = outputs(streams["srv"].url)["vmc"]
    assert vmc["targets"] == [f"127.0.0.1:{streams['receiver'].port}", f"127.0.0.1:{streams['absent']}"]
    assert vmc["failed"] == 0 and vmc["bundles_sent"] >= 2 * len(got)


# -- bad outputs ------------------------------------------------------------------------------------------
def test_bad_outputs_are_one_line_each_and_the_service_runs_without_them(tmp_path):
    """Tried: a VRPN port another program holds, a VMC host that does not resolve, a VMC port out of range,
    and a performer whose tree is not human-shaped (the simulator's six-link chain). Each is one line from
    `flockcal serve`; the service serves and fits, and the good VMC receiver still gets its bundles, saying
    no bones are loaded."""
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    busy = holder.getsockname()[1]
    receiver = Receiver()
    log = tmp_path / "serve.log"
    proc = ServerProcess(["--device", "sim://bad?birds=6&model=linkage&motion=exercise&rate=60", "--birds", "6",
                          "--data-dir", str(tmp_path / "d"),
                          "--vrpn", str(busy), "--osc", "nohost.invalid,127.0.0.1:70000",
                          "--osc", f"127.0.0.1:{receiver.port}"], free_port(), log_path=log)
    try:
        proc.start()
        wait_connected(proc.url)
        assert httpx.post(proc.url + "/api/sessions", json={"performer": "Chain"}).status_code == 201
        settled(lambda: httpx.get(proc.url + "/api/status").json()["fits"], lambda n: n >= 10)
        st = settled(lambda: outputs(proc.url), lambda o: "human" in (o["humanoid"]["reason"] or ""))
        got = receiver.wait(lambda b: len(b) >= 5, since=time.monotonic())
        text = log.read_text()
    finally:
        proc.stop()
        receiver.close()
        holder.close()
    lines = [x for x in text.splitlines() if "not started" in x]
    assert len(lines) == 3, text
    assert any(f"VRPN not started: cannot listen on 127.0.0.1 port {busy}" in x and "--vrpn PORT" in x for x in lines)
    assert any("nohost.invalid" in x and "cannot resolve" in x for x in lines)
    assert any("70000" in x and "1 to 65535" in x for x in lines)
    assert st["vrpn"] is None and st["vmc"]["targets"] == [f"127.0.0.1:{receiver.port}"]
    assert len(st["problems"]) == 3
    assert not st["humanoid"]["streaming"] and "not human-shaped" in st["humanoid"]["reason"]
    assert len([x for x in text.splitlines() if "send no bones" in x]) == 1  # once, not once a fit
    assert all(b["/VMC/Ext/OK"][0] == 0 and "Hips" not in b for b in got)


# -- a stored fit ---------------------------------------------------------------------------------------------
def test_a_stopped_sessions_fit_without_a_humanoid_streams_once_frames_find_one(tmp_path):
    """A service restarted after a session has that session's stored fit, with no humanoid in it: the streams
    find it from the live frames. Tried: the fit (the same object throughout, as the snapshots hand it over)
    and frames fed in real time at 144 Hz from their first; the first frames alone find no humanoid (no
    elbow or knee bent yet), so the streams must look again as frames come, and have bones before 8 s of
    frames run out (about 2 s here on a quiet machine)."""
    from flockcal.frames import Frames
    from flockcal.server.outputs import Outputs
    from flockcal.simulator.body import HUMAN_PARENTS
    from flockcal.simulator.performer import Performer
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import calibrate

    p = Performer("human", "exercise", seed=3, rate_hz=144)
    t = np.arange(0, 8, 1 / 144)
    R, x, v = p.poses(t)
    acc = GramAccumulator(p.n_sensors)
    acc.add_poses(R, x, v)
    fit = calibrate(acc, hierarchy=HUMAN_PARENTS, root="pelvis", names=p.names)
    assert fit.humanoid is None

    class Stored:  # what the snapshots show with no session live: the last session's final fit
        pose_fit, pose_fit_id, session = fit, ("stored", None), None

    out = Outputs(Settings(vrpn_port=0, data_dir=tmp_path), p.names, lambda: Stored, SYSTEM)
    out.start()
    try:
        start = time.monotonic()
        fed = 0
        while fed < len(t) and not out.status()["humanoid"]["streaming"]:
            due = min(len(t), int((time.monotonic() - start) * 144) + 1)
            out.feed(Frames(t[fed:due], R[fed:due], x[fed:due], v[fed:due]))
            fed = due
            time.sleep(0.005)
        assert out.status()["humanoid"]["streaming"], f"no bones after {fed / 144:.1f} s of frames: {out.reason}"
    finally:
        out.stop()


# -- the hand-over on the pipeline thread -----------------------------------------------------------------
def test_with_no_frames_the_pipeline_hands_over_to_the_streams_when_they_ask_and_not_before(tmp_path):
    """The streams' work rides on the pipeline thread's steps (`Pipeline.start(beside=…)`); a tracker gone
    quiet still gets VMC's bundles because the pipeline also runs the hand-over when the time it returned
    comes. Tried: a pipeline with no frames at all and a hand-over that asks again 10 ms on, 30 times: each
    it runs on its own comes no sooner than asked (an idle step, twice a second, runs it as every step does,
    whenever it comes: a loaded machine stretches the 30 past one) and most long before the next idle step,
    and the snapshots stay at their idle rate, not one per hand-over."""
    from flockcal.drivers.tracker_status import TrackerStatus
    from flockcal.server.limits import DiskStatus
    from flockcal.server.pipeline import Pipeline
    from flockcal.server.snapshot import SourceStatus
    from flockcal.server.store import Store

    calls, asked, published, seen = [], [], [], []

    def hand_over() -> float:
        calls.append(SYSTEM.monotonic())
        seen.append(len(published))  # a step's hand-over is followed by its snapshot before the next call
        asked.append(calls[-1] + 0.01)
        return asked[-1]

    store = Store(tmp_path / "flockcal.sqlite3")
    pipe = Pipeline(("a", "b"), store, lambda: SourceStatus(TrackerStatus(connected=True), "test", False,
                                                            DiskStatus(False, None, 0)),
                    on_publish=lambda snap: published.append(SYSTEM.monotonic()))
    pipe.start(beside=hand_over)
    try:
        wait_for(lambda: len(calls) >= 32, 60, "32 hand-overs with no frames")
    finally:
        pipe.stop()
        store.close()
    own = [k for k in range(1, 31) if seen[k + 1] == seen[k]]  # no snapshot after it: run on its own
    assert len(own) >= 25 and all(calls[k] >= asked[k - 1] for k in own), (own, np.diff(calls[:31]))
    # Not merely at the idle steps (twice a second): at the time asked, give or take a loaded machine's wake-up.
    assert np.median(np.diff(calls[:31])) < 0.25, np.diff(calls[:31])
    span = calls[30] - calls[0]
    assert sum(calls[0] < t <= calls[30] for t in published) <= span / 0.5 + 1, (published, span)
