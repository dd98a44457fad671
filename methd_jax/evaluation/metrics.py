"""Table 5.1 from per-episode results, with the thesis's numbers beside ours.

Definitions (per episode; see ``engine.RESULT_FIELDS``): T_pos is the time from the request to the
base within the goal tolerance of the HIP (requests never reached have none and are not served);
distance to HIP is the straight-line distance from the base to the HIP at the request; total
travelled sums the base's path over the whole run; a request is served when the arm finished while
it was active; collisions count the times the base ran into an obstacle (walls and furniture are
solid: it stops at them; a contact ends 1 cm clear) or the footprint touched a user's body; Escape
activations count every entry into Escape. Beyond the thesis: the base's yaw error to the HIP at
the request (the navigator turns the base after it), Inform activations, the time some user was
within the critical distance, and the closest any user came.
"""

from __future__ import annotations

import math

import numpy as np

THESIS = {
    "SU Static": {"t_pos": (4.84, 2.27), "distance_to_hip": (4.28, 3.29), "travelled": 827, "served": 99,
                  "requested": 100, "collisions": 0, "escapes": 166},
    "SU Heuristic": {"t_pos": (3.25, 0.73), "distance_to_hip": (2.35, 0.41), "travelled": 1824,
                     "served": 99, "requested": 100, "collisions": 0, "escapes": 214},
    "SU DRL": {"t_pos": (0.90, 0.22), "distance_to_hip": (1e-4, 7e-4), "travelled": 1909, "served": 100,
               "requested": 100, "collisions": 0, "escapes": 3},
    "MU Static": {"t_pos": (6.04, 3.07), "distance_to_hip": (5.46, 4.77), "travelled": 804, "served": 100,
                  "requested": 100, "collisions": 0, "escapes": 128},
    "MU DRL": {"t_pos": (1.07, 1.39), "distance_to_hip": (3e-3, 0.44), "travelled": 1882, "served": 100,
               "requested": 100, "collisions": 0, "escapes": 15},
}  # fmt: skip
"""Thesis Table 5.1 (Gazebo + ROS, 100 recorded test trajectories)."""


def median_iqr(values: np.ndarray) -> tuple[float, float]:
    """Median and interquartile range of the finite values (nan, nan if none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return math.nan, math.nan
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return float(med), float(q3 - q1)


def summary(results: dict[str, np.ndarray]) -> dict:
    """The Table 5.1 quantities (and ours beyond it) of one method's run."""
    requested = np.isfinite(results["request_time"])
    return {
        "t_pos": median_iqr(results["t_pos"]),
        "distance_to_hip": median_iqr(results["distance_to_hip"]),
        "yaw_to_hip": median_iqr(results["yaw_to_hip"]),
        "travelled": float(np.sum(results["travelled"])),
        "served": int(np.sum(results["served"])),
        "requested": int(np.sum(requested)),
        "collisions": int(np.sum(results["collisions_obstacle"]) + np.sum(results["collisions_user"])),
        "collisions_obstacle": int(np.sum(results["collisions_obstacle"])),
        "collisions_user": int(np.sum(results["collisions_user"])),
        "escapes": int(np.sum(results["escapes"])),
        "informs": int(np.sum(results["informs"])),
        "critical_time": float(np.sum(results["critical_time"])),
        "min_user_distance": float(np.min(results["min_user_distance"])),
        "episodes": len(results["served"]),
        "duration": float(np.sum(results["duration"])),
    }


def _num(x: float) -> str:
    if not math.isfinite(x):
        return "-"
    if x != 0 and abs(x) < 0.01:
        return f"{x:.0e}"
    return f"{x:.2f}"


ROWS = (
    ("Haptic positioning time T_pos, median [IQR] s (lower is better)", "t_pos"),
    ("Distance to HIP, median [IQR] m (lower is better)", "distance_to_hip"),
    ("Yaw error to the HIP at the request, median [IQR] rad (beyond the thesis)", "yaw_to_hip"),
    ("Total travelled distance, m (lower is better)", "travelled"),
    ("Successful haptic serves: served (requested) (higher is better)", "served"),
    ("Robot collisions: all (obstacles + users) (lower is better)", "collisions"),
    ("Escape activations (lower is better)", "escapes"),
    ("Inform activations (beyond the thesis)", "informs"),
    ("Time within d_crit = 1.77 m, s (beyond the thesis)", "critical_time"),
    ("Closest user-robot distance, m (beyond the thesis)", "min_user_distance"),
)


def _cell(s: dict | None, key: str) -> str:
    if s is None or key not in s:
        return "-"
    v = s[key]
    if key in ("t_pos", "distance_to_hip", "yaw_to_hip"):
        return f"{_num(v[0])} [{_num(v[1])}]"
    if key == "served":
        return f"{v} ({s['requested']})"
    if key == "collisions" and "collisions_user" in s:  # the thesis gives the total alone
        return f"{v} ({s['collisions_obstacle']} + {s['collisions_user']})"
    if key == "travelled":
        return f"{v:.0f}"
    if isinstance(v, float):
        return _num(v)
    return str(v)


def table_markdown(summaries: dict[str, dict]) -> str:
    """Table 5.1 as Markdown: for each method our value, then the thesis's in parentheses."""
    names = list(summaries)
    head = "| metric | " + " | ".join(f"{n} (ours) | {n} (thesis)" for n in names) + " |"
    rule = "|---|" + "---|---|" * len(names)
    lines = [head, rule]
    for label, key in ROWS:
        cells = []
        for n in names:
            cells += [_cell(summaries[n], key), _cell(THESIS.get(n), key)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
