"""The humanoid finding's oracle for tests and benchmarks: which bone each simulated body and each knee-trial
cluster is (written out, never read from solver/humanoid.py), takes renamed and re-plugged, and the swapped
hand names of the service and page tests."""

from __future__ import annotations

import numpy as np

from flockcal.simulator.body import HUMAN_NAMES
from flockcal.takes import make_take

SIM_BONE = {"pelvis": "hips", "abdomen": "spine", "chest": "chest", "head": "head",
            "l_upper_arm": "leftUpperArm", "l_forearm": "leftLowerArm", "l_hand": "leftHand",
            "r_upper_arm": "rightUpperArm", "r_forearm": "rightLowerArm", "r_hand": "rightHand",
            "l_thigh": "leftUpperLeg", "l_shin": "leftLowerLeg", "l_foot": "leftFoot",
            "r_thigh": "rightUpperLeg", "r_shin": "rightLowerLeg", "r_foot": "rightFoot"}
KNEE_BONE = {"pelvis": "hips", "thorax": "chest", "head": "head",
             "l_thigh": "leftUpperLeg", "l_shank": "leftLowerLeg", "l_foot": "leftFoot",
             "r_thigh": "rightUpperLeg", "r_shank": "rightLowerLeg", "r_foot": "rightFoot",
             "l_upper_arm": "leftUpperArm", "l_forearm": "leftLowerArm", "l_hand": "leftHand",
             "r_upper_arm": "rightUpperArm", "r_forearm": "rightLowerArm", "r_hand": "rightHand"}


def swapped_hands() -> tuple[list[str], dict[str, str]]:
    """The simulator's names in port order with the two hands' swapped (an operator's slip), and the bone
    each name's sensor really is: ({sensor name: bone})."""
    names = list(HUMAN_NAMES)
    a, b = names.index("l_hand"), names.index("r_hand")
    names[a], names[b] = names[b], names[a]
    return names, {names[k]: SIM_BONE[body] for k, body in enumerate(HUMAN_NAMES)}


def shuffled(take, seed: int, prefix: str = "bird"):
    """The take on other ports under meaningless names (`prefix` and a number): (take, the original name of
    the body at each new port)."""
    rng = np.random.default_rng([seed, 4747])
    perm = rng.permutation(take.n_sensors)
    names = [f"{prefix}{k}" for k in rng.permutation(take.n_sensors)]
    out = make_take(take.rotations[:, perm], take.positions[:, perm], names, take.rate_hz,
                    valid=take.valid[:, perm], times=take.times)
    return out, [take.names[p] for p in perm]
