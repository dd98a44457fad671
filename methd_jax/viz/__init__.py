"""See what the robot does: record an episode, draw it, animate it, open it in Foxglove.

- :class:`Rollout` (``methd_jax.viz.episode``): one episode of ``su``, ``nav`` or ``guide`` as numpy
  arrays; :func:`envs.record` records one from an environment, driven by any
  ``policy(obs) -> action``;
- :func:`frame`, :func:`animate`, :func:`polar_scan`, :func:`user_weight` (``methd_jax.viz.draw``): a
  top-down PNG of one step, a GIF (or MP4 with ffmpeg) of the episode, a LiDAR scan in polar form,
  u_w over time against who requested (matplotlib);
- :func:`to_mcap` (``methd_jax.viz.foxglove``): the episode as MCAP with Foxglove's schemas.

``python -m train.rollout`` does all of it from the command line for a run folder.
"""

from methd_jax.viz.draw import animate, draw_floor, frame, polar_scan, user_weight
from methd_jax.viz.episode import Rollout
from methd_jax.viz.foxglove import to_mcap

__all__ = [
    "Rollout",
    "animate",
    "draw_floor",
    "frame",
    "polar_scan",
    "to_mcap",
    "user_weight",
]
