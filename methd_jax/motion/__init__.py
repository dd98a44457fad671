"""Human motion data: synthetic and recorded walk-and-interact trajectories (thesis §4.3.1).

- :func:`synthesize` makes trajectories with the thesis dataset's statistics in the lab twin;
- :func:`save` / :func:`load` write and read them as ROS 2 bags in MCAP (:mod:`.bags` for the
  layout), :func:`convert` turns ROS 1 ``.bag`` recordings into that layout;
- :func:`default_dataset` is the 442-trajectory synthetic set (cached), :func:`sample` the few
  shipped in ``assets/``, :func:`split` the thesis's 342 / 100 split;
- :class:`MotionBank` packs the 50 Hz features the environments index on device.

Command line: ``python -m methd_jax.motion synth|stats|convert`` (``--help`` for each).
"""

from methd_jax.motion.bags import convert, load, save
from methd_jax.motion.dataset import default_dataset, sample, split
from methd_jax.motion.features import HipConfig, MotionBank, user_features
from methd_jax.motion.synth import SynthConfig, synthesize
from methd_jax.motion.trajectory import MotionDataError, TrackingGlitchWarning, Trajectory

__all__ = [
    "HipConfig",
    "MotionBank",
    "MotionDataError",
    "SynthConfig",
    "TrackingGlitchWarning",
    "Trajectory",
    "convert",
    "default_dataset",
    "load",
    "sample",
    "save",
    "split",
    "synthesize",
    "user_features",
]
