"""Top-down pictures of a :class:`~methd_jax.viz.episode.Rollout` (matplotlib, no display needed).

``frame(rollout, i, path)`` draws step ``i``: the floor's obstacles, the robot's footprint and
heading, the LiDAR returns, every user with the collision (d_coll) and critical (d_crit) circles and
the view direction, the HIPs (the requester's filled once requested) and the goal pose; GuideRL
rollouts add a u_w gauge. ``animate(rollout, path)`` writes the episode as a GIF with Pillow (a
matplotlib dependency, no system binary) or as MP4 when ffmpeg is installed. ``polar_scan`` plots a
LiDAR scan in the robot frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from methd_jax.viz.episode import Rollout

USER_COLOURS = ("#d1495b", "#2e86ab", "#66a182", "#edae49")
ROBOT_COLOUR = "#30343f"
OBSTACLE_COLOUR = "#8d99ae"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _rectangle(pose: np.ndarray, length: float, width: float) -> np.ndarray:
    """(5, 2) closed outline of a length x width box centred on ``pose``."""
    c = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]]) * [length / 2, width / 2]
    cos, sin = np.cos(pose[2]), np.sin(pose[2])
    return c @ np.array([[cos, sin], [-sin, cos]]) + pose[:2]


def _circle(x: float, y: float, r: float, n: int = 48) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n + 1)
    return np.stack([x + r * np.cos(a), y + r * np.sin(a)], 1)


def _arrow(pose: np.ndarray, length: float) -> np.ndarray:
    return np.stack([pose[:2], pose[:2] + length * np.array([np.cos(pose[2]), np.sin(pose[2])])])


def draw_floor(ax, floor) -> None:
    """Obstacles as filled shapes; the view framed on the floor's bounds plus its walls."""
    for (x, y, r), on in zip(floor.circles, floor.circle_mask, strict=True):
        if on:
            ax.fill(*_circle(x, y, r).T, color=OBSTACLE_COLOUR, lw=0)
    for poly, on, vmask in zip(floor.polygons, floor.polygon_mask, floor.vertex_mask, strict=True):
        if on:
            ax.fill(*poly[vmask].T, color=OBSTACLE_COLOUR, lw=0)
    x0, y0, x1, y1 = np.asarray(floor.bounds, float)
    pad = 0.4
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


class _Artists:
    """The moving parts of a frame, created once and updated per step (fast animations)."""

    def __init__(self, ax, rollout: Rollout):
        self.r = rollout
        plot = ax.plot
        self.trail = [
            plot([], [], "-", color=USER_COLOURS[j % len(USER_COLOURS)], lw=0.8, alpha=0.5)[0]
            for j in range(rollout.num_users)
        ]
        self.users = []
        for j in range(rollout.num_users):
            col = USER_COLOURS[j % len(USER_COLOURS)]
            self.users.append(
                {
                    "head": plot([], [], "o", color=col, ms=7, label=f"user {j + 1}")[0],
                    "view": plot([], [], "-", color=col, lw=2)[0],
                    "coll": plot([], [], "-", color=col, lw=1)[0],
                    "crit": plot([], [], "--", color=col, lw=0.8, alpha=0.7)[0],
                    "hip": plot([], [], "s", mec=col, mfc="none", ms=8, mew=1.5)[0],
                }
            )
        if rollout.robot is not None:
            self.hits = plot([], [], ".", color="#f26419", ms=2.5, label="LiDAR returns")[0]
            self.path = plot([], [], "-", color=ROBOT_COLOUR, lw=0.8, alpha=0.6)[0]
            self.body = plot([], [], "-", color=ROBOT_COLOUR, lw=2, label="robot")[0]
            self.heading = plot([], [], "-", color=ROBOT_COLOUR, lw=2)[0]
            self.goal = plot([], [], "*", color="#7b2cbf", ms=12, label="goal")[0]
            self.goal_dir = plot([], [], "-", color="#7b2cbf", lw=1.5)[0]
        self.text = ax.text(
            0.01, 0.99, "", transform=ax.transAxes, va="top", ha="left", fontsize=8, family="monospace"
        )
        ax.legend(loc="lower right", fontsize=7, framealpha=0.8)

    def update(self, i: int) -> None:
        r = self.r
        for j, a in enumerate(self.users):
            x, y = r.users[i, j, :2]
            a["head"].set_data([x], [y])
            a["view"].set_data(*_arrow(r.users[i, j], 0.6).T)
            a["coll"].set_data(*_circle(x, y, r.collision_distance).T)
            a["crit"].set_data(*_circle(x, y, r.critical_distance).T)
            hx, hy, _ = r.hips[i, j]
            a["hip"].set_data([hx], [hy])
            a["hip"].set_markerfacecolor(
                a["hip"].get_markeredgecolor() if r.requested[i] and j == r.requester else "none"
            )
            self.trail[j].set_data(r.users[: i + 1, j, 0], r.users[: i + 1, j, 1])
        lines = [f"{r.env}  t = {r.t[i]:5.2f} s"]
        if r.robot is not None:
            self.body.set_data(*_rectangle(r.robot[i], *r.footprint).T)
            self.heading.set_data(*_arrow(r.robot[i], 0.7).T)
            self.path.set_data(r.robot[: i + 1, 0], r.robot[: i + 1, 1])
            hits = r.hits(i)
            self.hits.set_data(hits[:, 0], hits[:, 1])
            self.goal.set_data([r.goal[i, 0]], [r.goal[i, 1]])
            self.goal_dir.set_data(*_arrow(r.goal[i], 0.5).T)
            d = np.linalg.norm(r.robot[i, :2] - r.goal[i, :2])
            lines.append(f"to goal {d:5.2f} m")
        if r.u_w is not None:
            lines.append(f"u_w {r.u_w[i]:+5.2f}")
        if r.requested[i]:
            lines.append(f"user {r.requester + 1} requested")
        if r.done[i]:
            lines.append(f"episode over: {r.outcome}")
        self.text.set_text("\n".join(lines))


def _figure(rollout: Rollout, size: tuple[int, int], dpi: int):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    draw_floor(ax, rollout.floor)
    artists = _Artists(ax, rollout)
    fig.tight_layout()
    return fig, artists


def _check_step(rollout: Rollout, i: int) -> int:
    if not -rollout.num_steps <= i < rollout.num_steps:
        raise IndexError(f"step {i} is outside the rollout's {rollout.num_steps} steps")
    return i % rollout.num_steps


def frame(rollout: Rollout, i: int = -1, path: str | Path | None = None, *, size=(720, 720), dpi: int = 100):
    """Step ``i`` as a figure (returned), written to ``path`` (PNG, ``size`` pixels) if given."""
    i = _check_step(rollout, i)
    fig, artists = _figure(rollout, size, dpi)
    artists.update(i)
    if path is not None:
        fig.savefig(path, dpi=dpi)
        _plt().close(fig)
    return fig


def animate(
    rollout: Rollout,
    path: str | Path,
    *,
    stride: int = 5,
    fps: int | None = None,
    size=(600, 600),
    dpi: int = 100,
    progress: bool = False,
) -> Path:
    """Every ``stride``-th step (and the last) to ``path``: ``.gif`` (Pillow) or ``.mp4`` (ffmpeg).
    ``fps`` defaults to real time (50 Hz control / stride)."""
    from matplotlib import animation

    path = Path(path)
    steps = rollout.strided(stride)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        writer_cls = animation.PillowWriter
    elif suffix == ".mp4":
        if not animation.FFMpegWriter.isAvailable():
            raise RuntimeError(
                "writing .mp4 needs ffmpeg on PATH (Debian: apt install ffmpeg); write a .gif instead"
            )
        writer_cls = animation.FFMpegWriter
    else:
        raise ValueError(f"{path}: animations are written as .gif or .mp4")
    dt = float(rollout.t[1] - rollout.t[0]) if rollout.num_steps > 1 else 0.02
    fps = fps or max(1, round(1.0 / (dt * stride)))
    fig, artists = _figure(rollout, size, dpi)
    writer = writer_cls(fps=fps)
    with writer.saving(fig, str(path), dpi):
        for n, i in enumerate(steps):
            artists.update(i)
            writer.grab_frame()
            if progress and (n % 20 == 0 or n == len(steps) - 1):
                print(f"\r  frame {n + 1}/{len(steps)}", end="", flush=True)
    if progress:
        print()
    _plt().close(fig)
    return path


def polar_scan(ranges, *, ax=None, max_range: float | None = None, label: str | None = None, path=None):
    """A LiDAR scan in the robot frame (ray i at 2 pi i / n, counter-clockwise, 0 = forward)."""
    plt = _plt()
    ranges = np.asarray(ranges, float)
    if ranges.ndim != 1 or len(ranges) < 2:
        raise ValueError(f"polar_scan needs one scan of at least 2 rays, got shape {ranges.shape}")
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(4.5, 4.5), subplot_kw={"projection": "polar"})
    angles = 2 * np.pi * np.arange(len(ranges)) / len(ranges)
    shown = np.where(np.isfinite(ranges), ranges, np.nan)
    ax.plot(np.append(angles, angles[0]), np.append(shown, shown[0]), lw=1, label=label)
    if max_range is not None:
        ax.set_rmax(max_range)
    ax.set_theta_zero_location("N")  # forward up, as a driver sees it
    ax.set_title("LiDAR scan (robot frame, forward up)", fontsize=9)
    if path is not None:
        (fig or ax.figure).savefig(path, dpi=100)
        plt.close(fig or ax.figure)
    return ax


def user_weight(rollout: Rollout, *, ax=None, path=None):
    """u_w over the episode against who requested (GuideRL and two-user NavRL): -1 is user 1,
    +1 user 2; the request is marked and the requester's side shaded."""
    if rollout.u_w is None:
        raise ValueError(f"a {rollout.env!r} rollout with {rollout.num_users} user(s) has no user weight u_w")
    plt = _plt()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.5, 2.8))
    ax.plot(rollout.t, rollout.u_w, color=ROBOT_COLOUR, lw=1.5, label="u_w")
    side = -1 if rollout.requester == 0 else 1
    ax.axhspan(
        0,
        side,
        color=USER_COLOURS[rollout.requester],
        alpha=0.12,
        label=f"user {rollout.requester + 1} (requester)",
    )
    if rollout.requested.any():
        t_req = rollout.t[np.argmax(rollout.requested)]
        ax.axvline(t_req, color="k", ls="--", lw=1, label="request")
    ax.set_ylim(-1.05, 1.05)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("u_w  (-1 user 1, +1 user 2)")
    ax.legend(loc="best", fontsize=7)
    if path is not None:
        (fig or ax.figure).tight_layout()
        (fig or ax.figure).savefig(path, dpi=100)
        plt.close(fig or ax.figure)
    return ax
