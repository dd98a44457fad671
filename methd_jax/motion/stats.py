"""Dataset statistics against the thesis's (§4.3.1, Fig. 4.10), and pictures of them."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from methd_jax.control import CONTROL_HZ
from methd_jax.motion.features import user_features
from methd_jax.motion.trajectory import GLITCH_SPEED, Trajectory


@dataclasses.dataclass(frozen=True)
class Target:
    mean: float
    sd: float | None = None


THESIS = {
    "duration_s": Target(21.9, 8.57),
    "path_length_m": Target(11.5, 6.63),
    "speed_mps": Target(0.5, 0.38),
}
"""The thesis dataset: 442 trajectories; speed median 0.6 m/s, max 1.9 m/s (outliers > 2 m/s dropped)."""
THESIS_SPEED_MEDIAN = 0.6
THESIS_SPEED_MAX = 1.9
MEAN_TOLERANCE = 0.10
"""Means must lie within 10% of the thesis's."""
SD_TOLERANCE = 0.25
"""Standard deviations must lie within 25% of the thesis's."""


def compute(trajectories: Sequence[Trajectory]) -> dict:
    """Per-trajectory durations and path lengths (up to the request) and speed samples (50 Hz,
    whole recordings, as in the thesis's Fig. 4.10).

    Speeds above 2 m/s (tracking errors, excluded by the thesis too) are dropped and counted.
    """
    durations, paths, speeds = [], [], []
    for t in trajectories:
        f = user_features(t)
        r = int(f["request_step"])
        v = np.linalg.norm(f["vel_world"][:, :2], axis=1)
        durations.append(t.duration)
        paths.append(float(np.sum(np.linalg.norm(np.diff(f["pose"][: r + 1, :2], axis=0), axis=1))))
        speeds.append(v)
    sp = np.concatenate(speeds)
    clean = sp[sp <= GLITCH_SPEED]
    d, p = np.asarray(durations), np.asarray(paths)
    return {
        "trajectories": len(trajectories),
        "duration_s": {"mean": d.mean(), "sd": d.std(ddof=1) if len(d) > 1 else 0.0, "values": d},
        "path_length_m": {"mean": p.mean(), "sd": p.std(ddof=1) if len(p) > 1 else 0.0, "values": p},
        "speed_mps": {
            "mean": clean.mean(),
            "sd": clean.std(),
            "median": float(np.median(clean)),
            "max": float(clean.max()),
            "outliers_dropped": int(sp.size - clean.size),
            "values": clean,
            "rate_hz": CONTROL_HZ,
        },
    }


def check(stats: dict) -> list[str]:
    """The ways ``stats`` misses the thesis's figures (empty when all hold)."""
    problems = []
    for key, target in THESIS.items():
        got = stats[key]
        if abs(got["mean"] - target.mean) > MEAN_TOLERANCE * target.mean:
            problems.append(f"{key} mean {got['mean']:.3f} is not within 10% of {target.mean}")
        if target.sd is not None and abs(got["sd"] - target.sd) > SD_TOLERANCE * target.sd:
            problems.append(f"{key} SD {got['sd']:.3f} is not within 25% of {target.sd}")
    med = stats["speed_mps"]["median"]
    if abs(med - THESIS_SPEED_MEDIAN) > MEAN_TOLERANCE * THESIS_SPEED_MEDIAN:
        problems.append(f"speed median {med:.3f} is not within 10% of {THESIS_SPEED_MEDIAN}")
    if stats["speed_mps"]["max"] > THESIS_SPEED_MAX:
        problems.append(f"speed max {stats['speed_mps']['max']:.3f} exceeds {THESIS_SPEED_MAX}")
    return problems


def report(stats: dict) -> str:
    """A table of the dataset's figures next to the thesis's."""
    rows = [f"{stats['trajectories']} trajectories", f"{'':18}{'this set':>18}{'thesis':>18}"]
    for key, label in (
        ("duration_s", "duration s"),
        ("path_length_m", "path length m"),
        ("speed_mps", "speed m/s"),
    ):
        got, want = stats[key], THESIS[key]
        rows.append(
            f"{label:18}{got['mean']:>9.2f} (SD {got['sd']:4.2f}){want.mean:>9.2f} (SD {want.sd:4.2f})"
        )
    sp = stats["speed_mps"]
    rows.append(f"{'speed median':18}{sp['median']:>18.2f}{THESIS_SPEED_MEDIAN:>18.2f}")
    rows.append(f"{'speed max':18}{sp['max']:>18.2f}{THESIS_SPEED_MAX:>18.2f}")
    rows.append(f"speeds > {GLITCH_SPEED} m/s dropped as tracking errors: {sp['outliers_dropped']}")
    problems = check(stats)
    rows.append("matches the thesis (means within 10%, SDs within 25%)" if not problems else "MISMATCH:")
    rows += [f"  - {p}" for p in problems]
    return "\n".join(rows)


def plot(stats: dict, trajectories: Sequence[Trajectory], out_dir: str | Path, floor=None, n_paths: int = 6):
    """Writes ``speed_boxplot.png`` and ``trajectories.png`` to ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from methd_jax import floors

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(3.2, 4.2))
    ax.boxplot(stats["speed_mps"]["values"], showfliers=True, medianprops={"color": "tab:orange"})
    ax.set_ylabel("user speed (m/s)")
    ax.set_xticks([1], [f"{stats['trajectories']} trajectories"])
    ax.set_title("Speeds (cf. thesis Fig. 4.10)", fontsize=9)
    fig.tight_layout()
    box = out / "speed_boxplot.png"
    fig.savefig(box, dpi=120)
    plt.close(fig)

    floor = floors.lab() if floor is None else floor
    fig, ax = plt.subplots(figsize=(5.5, 6.2))
    circles, polygons = floor.primitives()
    for x, y, r in circles:
        ax.add_patch(plt.Circle((x, y), r, color="0.55"))
    for p in polygons:
        ax.add_patch(plt.Polygon(p, color="0.55"))
    for t in trajectories[:n_paths]:
        (line,) = ax.plot(t.head[:, 0], t.head[:, 1], lw=1.2, label=t.name)
        i = t.request_index
        ax.plot(t.head[0, 0], t.head[0, 1], "o", color=line.get_color(), ms=4)
        ax.plot(t.head[i, 0], t.head[i, 1], "*", color=line.get_color(), ms=11, mec="k", mew=0.5)
    b = np.asarray(floor.bounds)
    ax.set_xlim(b[0] - 0.4, b[2] + 0.4)
    ax.set_ylim(b[1] - 0.4, b[3] + 0.4)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Head paths (o start, * haptic request)", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    paths = out / "trajectories.png"
    fig.savefig(paths, dpi=120)
    plt.close(fig)
    return [box, paths]
