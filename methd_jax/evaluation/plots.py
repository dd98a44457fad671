"""Figures 5.3-5.6 of the thesis from evaluation results (matplotlib, written to PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _groups(summaries: dict[str, dict]) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = {"SU": [], "MU": []}
    for name in summaries:
        groups[name.split()[0] if name.split()[0] in groups else "SU"].append(name)
    return {k: v for k, v in groups.items() if v}


def bars(summaries: dict[str, dict], key: str, ylabel: str, title: str, path: Path) -> Path:
    """One bar per method, SU and MU side by side (Figures 5.3 and 5.4)."""
    plt = _plt()
    groups = _groups(summaries)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.5 * len(groups), 3.6), squeeze=False)
    for ax, (group, names) in zip(axes[0], groups.items(), strict=True):
        values = [summaries[n][key] for n in names]
        labels = [n.split(" ", 1)[1] if " " in n else n for n in names]
        rects = ax.bar(labels, values, color=["#9aa5b1", "#e0a458", "#2e86ab"][: len(names)])
        ax.bar_label(rects, fmt="%.0f")
        ax.set_title(group)
        ax.set_ylabel(ylabel)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def boxes(results: dict[str, dict], key: str, ylabel: str, title: str, path: Path) -> Path:
    """Box plots per method, SU on top and MU below (Figures 5.5 and 5.6)."""
    plt = _plt()
    groups = _groups(results)
    fig, axes = plt.subplots(len(groups), 1, figsize=(6.0, 3.2 * len(groups)), squeeze=False)
    for ax, (group, names) in zip(axes[:, 0], groups.items(), strict=True):
        data = []
        for n in names:
            v = np.asarray(results[n][key], np.float64)
            data.append(v[np.isfinite(v)])
        labels = [n.split(" ", 1)[1] if " " in n else n for n in names]
        ax.boxplot(data, tick_labels=labels, showfliers=True)
        ax.set_title(group)
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def figures(results: dict[str, dict], summaries: dict[str, dict], folder: Path) -> list[Path]:
    """Write the four figures into ``folder``; returns their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [
        bars(summaries, "escapes", "activations", "Escape activations (Fig. 5.3)", folder / "escapes.png"),
        bars(summaries, "travelled", "m", "Total travelled distance (Fig. 5.4)", folder / "travelled.png"),
        boxes(results, "distance_to_hip", "m", "Distance to HIP at the request (Fig. 5.5)",
              folder / "distance_to_hip.png"),
        boxes(results, "t_pos", "s", "Haptic positioning time T_pos (Fig. 5.6)", folder / "t_pos.png"),
    ]  # fmt: skip
