"""Goal poses from the user weight u_w (GuideRL, thesis §4.2.2), shared by ``guide`` and ``nav``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from methd_jax.geometry import wrap_angle

SWITCH = 0.25
"""|u_w| beyond which the goal takes the nearer user's HIP yaw outright (eq. 4.23)."""


def blend_yaw(yaw1: jax.Array, yaw2: jax.Array) -> jax.Array:
    """Psi of eq. 4.23: the circular mean of two yaws.

    The thesis prints ``arctan((sin t1 + cos t2) / (cos t1 + sin t2))``, which gives pi/4 for two
    equal yaws of 0 and so cannot be the "stable interpolation between the two angles" the text
    describes; we read it as the circular mean ``atan2(sin t1 + sin t2, cos t1 + cos t2)``.
    """
    return jnp.arctan2(jnp.sin(yaw1) + jnp.sin(yaw2), jnp.cos(yaw1) + jnp.cos(yaw2))


def goal_from_weight(u_w: jax.Array, hip1: jax.Array, hip2: jax.Array) -> jax.Array:
    """Goal pose (x, y, yaw) on the segment between two HIPs: u_w = -1 user 1, +1 user 2, 0 the midpoint."""
    xy = hip1[:2] + 0.5 * (u_w + 1.0) * (hip2[:2] - hip1[:2])
    yaw = jnp.where(u_w < -SWITCH, hip1[2], jnp.where(u_w > SWITCH, hip2[2], blend_yaw(hip1[2], hip2[2])))
    return jnp.concatenate([xy, wrap_angle(yaw)[None]])
