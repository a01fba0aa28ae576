"""VMC protocol out: the live humanoid as OSC bundles over UDP to VMC receivers (EVMC4U, VMC4UE, VMC4B, Godot's),
laid out by python-osc once per set of bones and refilled in place each frame, sent fire-and-forget
(docs/streams.md#vmc-the-live-humanoid-over-the-vmc-protocol).
"""

from __future__ import annotations

import ipaddress
import logging
import socket
from dataclasses import dataclass

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from flockcal.rotations import as_quat

log = logging.getLogger(__name__)

DEFAULT_PORT = 39539  # where VMC receivers (the protocol's "Marionette") listen

# VRM 1.0 humanoid bone → Unity's HumanBodyBones name, what VMC's /VMC/Ext/Bone/Pos names a bone by.
UNITY_BONES = {
    "hips": "Hips", "spine": "Spine", "chest": "Chest", "head": "Head",
    "leftUpperArm": "LeftUpperArm", "leftLowerArm": "LeftLowerArm", "leftHand": "LeftHand",
    "rightUpperArm": "RightUpperArm", "rightLowerArm": "RightLowerArm", "rightHand": "RightHand",
    "leftUpperLeg": "LeftUpperLeg", "leftLowerLeg": "LeftLowerLeg", "leftFoot": "LeftFoot",
    "rightUpperLeg": "RightUpperLeg", "rightLowerLeg": "RightLowerLeg", "rightFoot": "RightFoot",
}

# /VMC/Ext/OK's calibration state (VMC protocol v2.5).
UNCALIBRATED, WAITING, CALIBRATING, CALIBRATED = 0, 1, 2, 3

# The humanoid's world (right-handed: +X the performer's left, +Y up, +Z forward) to Unity's (left-handed:
# +X right, +Y up, +Z forward) is the mirror x → −x: positions negate x; a rotation's axis, a pseudovector,
# keeps x and negates y and z, so a quaternion (x, y, z, w) becomes (x, −y, −z, w).
UNITY_POSITION = np.array([-1.0, 1.0, 1.0])
UNITY_QUATERNION = np.array([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Target:
    """A receiver: as the user gave it, and the socket address it resolved to."""

    spec: str
    host: str
    port: int
    family: int
    address: tuple

    @property
    def label(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


def parse_targets(specs) -> tuple[list[Target], list[str]]:
    """The receivers of `--osc` values (each HOST[:PORT], several separated by commas; an IPv6 address in
    brackets when a port follows), and one line for each that cannot be used (a bad port, a host name that
    does not resolve), naming it and the fix."""
    targets, problems = [], []
    for spec in (part.strip() for value in specs for part in str(value).split(",")):
        if not spec:
            continue
        try:
            host, port = split_target(spec)
            family, _type, _proto, _name, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        except ValueError as exc:
            problems.append(f"VMC output to {spec!r} not started: {exc}; give --osc HOST or HOST:PORT")
            continue
        except (socket.gaierror, UnicodeError) as exc:
            why = exc.strerror if isinstance(exc, socket.gaierror) else str(exc)
            problems.append(f"VMC output to {spec!r} not started: cannot resolve host {host!r} ({why}); "
                            "check the name in --osc")
            continue
        targets.append(Target(spec, host, port, family, address))
    return targets, problems


def split_target(spec: str) -> tuple[str, int]:
    """(host, port) of HOST, HOST:PORT, [IPv6]:PORT or a bare IPv6 address; ValueError naming what is wrong."""
    if spec.startswith("["):
        host, sep, rest = spec[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise ValueError("an IPv6 address in brackets is [ADDRESS] or [ADDRESS]:PORT")
        port_text = rest[1:] if rest else ""
    elif spec.count(":") > 1:  # a bare IPv6 address: no port can follow it unbracketed
        ipaddress.IPv6Address(spec)
        host, port_text = spec, ""
    else:
        host, _sep, port_text = spec.partition(":")
    if not host:
        raise ValueError("no host")
    if not port_text:
        return host, DEFAULT_PORT
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise ValueError(f"port {port_text!r} is not a number from 1 to 65535")
    return host, int(port_text)


def vmc_bones(rig, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(K, 7) /VMC/Ext/Bone/Pos numbers of the rig's K present bones in one frame: `BoneLayout(rig).numbers`."""
    return BoneLayout(rig).numbers(positions, rotations)


class BoneLayout:
    """What a frame's /VMC/Ext/Bone/Pos numbers take from a rig (solver/humanoid_pose.py), worked out once per
    rig: the present bones' Unity names, each one's parent bone (its slot among them) and T-pose offset.

    `numbers` gives position x y z and quaternion x y z w per bone, in Unity's frame, each bone local to its
    parent bone with the T-pose as rest (every bone's rest rotation the identity, VRM's normalized rest): its
    rotation R_parentᵀ R, its position the T-pose offset from its parent bone's start (a limb's: the fitted
    bone's length). The hips are local to the root, which /VMC/Ext/Root/Pos puts at the origin unturned:
    their world position and rotation."""

    def __init__(self, rig):
        from flockcal.solver.humanoid import BONES

        present = rig.present
        self.names = tuple(UNITY_BONES[BONES[k]] for k in present)
        slot = np.full(len(rig.sensor), -1)
        slot[present] = np.arange(len(present))
        parent = rig.parent_bone[present]
        self.has = parent >= 0
        self.up = slot[parent[self.has]]
        self.offsets = rig.local_offset[present] * UNITY_POSITION
        # Indices, not masks, and the numbers' constant part laid out once: the streams call `local` and
        # `assemble` 60 times a second, where each numpy call's overhead is the cost.
        self._child, self._root = _as_slice(np.flatnonzero(self.has)), _as_slice(np.flatnonzero(~self.has))
        self._template = np.zeros((len(self.has), 7))
        self._template[:, :3] = self.offsets

    def numbers(self, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """From the bones' segments in one frame: (K, 3) positions, (K, 3, 3) rotations on the humanoid's world
        axes (`HumanoidRig.segments`)."""
        return self.assemble(positions, as_quat(self.local(rotations), scalar_first=False))

    def local(self, rotations: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(K, 3, 3) each bone's rotation local to its parent bone (the hips': their own), still on the
        humanoid's axes: what `assemble` takes as quaternions (the streams turn them in one call with VRPN's,
        written with `out` straight into that call's input)."""
        if out is None:
            out = np.empty_like(rotations)
        out[self._root] = rotations[self._root]
        out[self._child] = np.swapaxes(rotations[self.up], -1, -2) @ rotations[self._child]
        return out

    def assemble(self, positions: np.ndarray, local_quats: np.ndarray) -> np.ndarray:
        """(K, 7) numbers from one frame's (K, 3) segment positions and (K, 4) quaternions x y z w of `local`."""
        out = self._template.copy()
        out[self._root, :3] = positions[self._root] * UNITY_POSITION
        np.multiply(local_quats, UNITY_QUATERNION, out=out[:, 3:])
        return out


class Bundle:
    """One frame's bundle for a set of bones: /VMC/Ext/OK (loaded, calibration state, calibration mode,
    tracking status), /VMC/Ext/T, /VMC/Ext/Root/Pos and one /VMC/Ext/Bone/Pos per bone, laid out once by
    python-osc; `fill` writes a frame's numbers into it in place (every number is 4-byte aligned in OSC). With
    all 16 bones it is 1384 bytes: one datagram, under an Ethernet frame's 1472-byte UDP payload."""

    def __init__(self, bones: tuple[str, ...]):
        self.bones = bones
        messages = [_message("/VMC/Ext/OK", [(0, "i")] * 4), _message("/VMC/Ext/T", [(0.0, "f")])]
        if bones:
            messages.append(_message("/VMC/Ext/Root/Pos", [("root", "s")] + [(0.0, "f")] * 7))
            messages += [_message("/VMC/Ext/Bone/Pos", [(name, "s")] + [(0.0, "f")] * 7) for name in bones]
        builder = OscBundleBuilder(IMMEDIATELY)
        for m in messages:
            builder.add_content(m)
        self.data = bytearray(builder.build().dgram)
        # Where each message's numbers end: walk the bundle's elements (a 4-byte size, then the message).
        ends, at = [], 16
        for m in messages:
            size = int.from_bytes(self.data[at:at + 4], "big")
            assert size == len(m.dgram)
            at += 4 + size
            ends.append(at // 4)
        self._ints = np.frombuffer(self.data, dtype=">i4")
        self._floats = np.frombuffer(self.data, dtype=">f4")
        self._ok = slice(ends[0] - 4, ends[0])  # /VMC/Ext/OK's four ints, side by side
        self._t = ends[1] - 1
        self._poses = np.array([np.arange(e - 7, e) for e in ends[2:]]).reshape(-1, 7)
        if bones:  # the root stays at the origin, unturned
            self._floats[self._poses[0]] = (0, 0, 0, 0, 0, 0, 1)
        self._bones = self._poses[1:]

    @property
    def size(self) -> int:
        return len(self.data)

    def fill(self, ok: tuple[int, int, int, int], t: float, bones: np.ndarray | None = None) -> bytearray:
        """The bundle with these numbers: `bones` (K, 7) in `self.bones` order (the root stays at the origin)."""
        self._ints[self._ok] = ok
        self._floats[self._t] = t
        if self.bones:
            self._floats[self._bones] = bones
        return self.data


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """`index` as a slice where it is a run of consecutive indices (the hips first, every other bone after
    them, as a rig has them): read and written as a view, not gathered and scattered."""
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


def _message(address: str, args: list[tuple]) -> object:
    m = OscMessageBuilder(address)
    for value, kind in args:
        m.add_arg(value, kind)
    return m.build()


class VmcSender:
    """Sends each bundle to every target from one non-blocking UDP socket per address family."""

    def __init__(self, targets: list[Target]):
        self.targets = targets
        self.sent = 0
        self.failed = 0
        self.last_error: str | None = None
        self._sockets: dict[int, socket.socket] = {}
        for t in targets:
            if t.family not in self._sockets:
                s = socket.socket(t.family, socket.SOCK_DGRAM)
                s.setblocking(False)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)  # a subnet's broadcast address is a target too
                self._sockets[t.family] = s

    def send(self, data) -> None:
        for t in self.targets:
            try:
                self._sockets[t.family].sendto(data, t.address)
                self.sent += 1
            except (BlockingIOError, InterruptedError):
                self.failed += 1  # the socket's buffer is full: this frame is lost, the next one goes
            except OSError as exc:  # no route, a refused port reported back: said once a minute (logthrottle)
                self.failed += 1
                self.last_error = f"{t.label}: {exc.strerror or exc}"
                log.warning("VMC: cannot send to %s: %s", t.label, exc.strerror or exc)

    def close(self) -> None:
        for s in self._sockets.values():
            s.close()

    def status(self) -> dict:
        return {"targets": [t.label for t in self.targets], "bundles_sent": self.sent, "failed": self.failed,
                "last_error": self.last_error}
