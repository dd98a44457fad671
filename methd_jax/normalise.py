"""The observation normaliser, written once for training (JAX), export and the robot (numpy).

``normalise(x, mean, std, clip)`` is ``(x - mean) / std`` clipped to ``[-clip, clip]`` when
``clip > 0``. It uses only array operators and the ``.clip`` method, which numpy and JAX arrays
both have, so the same line runs under ``jit`` and on the robot without JAX.
"""


def normalise(x, mean, std, clip: float):
    """``(x - mean) / std``, clipped to ``[-clip, clip]`` when ``clip > 0``."""
    z = (x - mean) / std
    return z.clip(-clip, clip) if clip > 0 else z
