"""Plain words for the calibration: the sentences that tell an operator what to move next (readable body
and joint names are flockcal/names.py's). The numbers behind them (progress, done, what is missing) are defined in
server/progress.py; the pages' names (static/common.js) mirror the ones here.
"""

from __future__ import annotations


from flockcal.names import joint_label, joint_name, readable_body  # noqa: F401  (re-exported for server/progress.py)


def hint_sentence(item: dict) -> str:
    """The operator's sentence for one sensor whose joint is not calibrated yet (an entry of
    progress.standing: state, joint, parent, pinned, error_m, target_m, undone)."""
    label = joint_label(item["joint"], item.get("parent"))
    child, parent = readable_body(item["joint"]), readable_body(item.get("parent") or "")
    undone = item.get("undone")
    if undone and undone.get("reason") == "slip":
        return (f"The {readable_body(undone['sensor'])} sensor slipped at {undone['time_s']:.1f} s: "
                f"move {label} again so it is measured afresh.")
    if undone and undone.get("reason") == "loss":
        return f"Keep moving {label}: it no longer fits as well as when it was calibrated."
    state = item["state"]
    if state == "rigid":
        return f"Move {label}: the {child} has not moved relative to the {parent} yet."
    if state == "not_turned":
        return f"Move {label} more: it has hardly turned yet."
    if state == "undetermined":
        return (f"Move {label} more, in other directions too (twist and swing it, not only bend): "
                f"its centre is pinned along {item.get('pinned', 0)} of the 3 directions so far.")
    if state == "unsettled":
        return (f"Move the joints next to {label} too: it is pinned, but {item.get('unsettled')}, so which "
                "two bodies it joins is not settled yet.")
    if state == "confirming":
        return f"Keep moving {label}: it is pinned and counts in a moment."
    return f"Keep moving {label}: a little more and it is pinned down."
