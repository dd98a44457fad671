"""The control rate: one 50 Hz clock for the base, the environments, the motion features, the
rewards and the evaluation (thesis §4.3.2). Every period in the project derives from it; nothing
overrides it."""

CONTROL_HZ = 50.0
"""Control steps per second."""
CONTROL_DT = 1.0 / CONTROL_HZ
"""The control period, s."""
