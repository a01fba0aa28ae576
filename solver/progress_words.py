"""Calibration progress in plain words (solver/progress.py decides it, this says it): why a joint is not
calibrated yet, the operator's sentence of what to move next, the patient prompt of a stalled session,
and the session event of becoming calibrated or undone. Joints are named as the fit names them (a
humanoid's "left knee"), else, like bodies, as flockcal/names.py names them, which the pages share.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from flockcal.names import joint_label, joint_name, readable_body

if TYPE_CHECKING:
    from flockcal.solver.progress import Profile, Progress, Standing


def why_not_done(item: "Standing", target_m: float) -> str:
    """Why a sensor's joint is not calibrated, in one clause (its `why`)."""
    undone = item.undone
    if undone and undone.reason == "slip":
        return f"the {readable_body(undone.sensor)} sensor slipped at {undone.time_s:.1f} s: measured afresh since"
    if undone and undone.reason == "loss":
        return "no longer fits as it did when calibrated"
    if undone and undone.reason == "tree":
        return (f"the tree now joins it to the {readable_body(undone.parent)} "
                f"(it was calibrated against the {readable_body(undone.was)})")
    state = item.state
    if state == "rigid":
        return f"has not moved relative to the {readable_body(item.parent or '')} yet"
    if state == "not_turned":
        return "not determined: it has hardly turned yet"
    if state == "undetermined":
        return f"not determined: its centre is pinned along {item.pinned} of 3 directions"
    if state == "unsettled":
        return f"pinned, but its place in the tree is not settled: {item.unsettled}"
    if state == "confirming":
        return "pinned; counted once it holds for a moment"
    if state == "settling":
        return item.settling or "pinned; counted once more movement no longer changes it"
    return f"pinned to {1000 * item.error_m:.1f} mm, target {1000 * target_m:.1f} mm"


def the_joint(joint: str, parent: str | None, label: str) -> str:
    """The joint for a sentence: "the left knee"; "the joint between the bird 1 and the bird 2" where neither
    the fit (`label`) nor the sensors' names say more."""
    if label != joint_name(joint, parent):
        return f"the {label}"  # the fit's own name (a humanoid's)
    return joint_label(joint, parent)


def hint_sentence(item: "Standing") -> str:
    """The operator's sentence for one sensor whose joint is not calibrated yet."""
    label = the_joint(item.joint, item.parent, item.label)
    child, parent = readable_body(item.joint), readable_body(item.parent or "")
    undone = item.undone
    if undone and undone.reason == "slip":
        return (f"The {readable_body(undone.sensor)} sensor slipped at {undone.time_s:.1f} s: "
                f"move {label} again so it is measured afresh.")
    if undone and undone.reason == "loss":
        return f"Keep moving {label}: it no longer fits as well as when it was calibrated."
    state = item.state
    if state == "rigid":
        return f"Move {label}: the {child} has not moved relative to the {parent} yet."
    if state == "not_turned":
        return f"Move {label} more: it has hardly turned yet."
    if state == "undetermined":
        return (f"Move {label} more, in other directions too (twist and swing it, not only bend): "
                f"its centre is pinned along {item.pinned} of the 3 directions so far.")
    if state == "unsettled":
        return (f"Move the joints next to {label} too: it is pinned, but {item.unsettled}, so which "
                "two bodies it joins is not settled yet.")
    if state == "confirming":
        return f"Keep moving {label}: it is pinned and counts in a moment."
    return f"Keep moving {label}: a little more and it is pinned down."


def stall_prompt(joint: str, parent: str | None, label: str | None = None) -> str:
    """The kiosk's patient prompt once the ring has stalled, naming the first joint still missing (`label`:
    as the fit names it)."""
    return (f"Take your time and keep going: big, slow movements of your "
            f"{label or joint_name(joint, parent)}, every way it bends.")


def done_change(progress: "Progress", was_done: bool, performer: str, prof: "Profile",
                time_s: float) -> tuple[str, str] | None:
    """(action, message) of the session event when `progress` became done ("calibrated") or stopped being
    so ("calibration_undone", saying why); None when neither."""
    if progress.done and not was_done:
        how = (f"pinned to {1000 * prof.target_m:.1f} mm" if prof.steady is None else
               f"pinned to {1000 * prof.tolerance_m:.0f} mm and steady")
        return ("calibrated",
                f"{performer} is calibrated: all {progress.joints_needed} joints {how} after {time_s:.1f} s")
    if was_done and not progress.done:
        missing = progress.missing_joints()
        why = next((m.why for m in missing if m.undone), None)
        if why is None and missing:
            why = f"{missing[0].label}: {missing[0].why}"
        return "calibration_undone", f"{performer} is no longer calibrated: {why or 'a joint was undone'}"
    return None
