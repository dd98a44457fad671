"""The thesis's evaluation (Chapter 5): behaviour engine, navigator, baselines, metrics, statistics.

- :mod:`.navigator`: costmap, wavefront planner and path follower (the ROS navigation stack's role);
- :mod:`.methods`: positioning methods in Chase: :class:`Static`, :class:`Heuristic`, :class:`Policy`;
- :mod:`.engine`: Chase / Haptic / Arm / Escape / Inform at 50 Hz over a schedule of episodes;
- :mod:`.metrics`: Table 5.1's rows from per-episode results; :mod:`.stats`: Friedman, Kendall's W,
  Wilcoxon signed-rank with Holm's correction.

``python -m train.evaluate`` puts it together.
"""
