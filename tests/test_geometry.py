import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methd_jax import geometry
from methd_jax.geometry import KAIROS, Footprint

HALF_L, HALF_W = 1.13 / 2, 0.91 / 2


def test_wrap_angle_range_and_identity():
    a = jnp.linspace(-20, 20, 1001)
    w = geometry.wrap_angle(a)
    assert jnp.all(w >= -jnp.pi) and jnp.all(w < jnp.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-5)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-5)


def test_se2_round_trips():
    key = jax.random.key(0)
    poses = jax.random.uniform(key, (50, 3), minval=-4, maxval=4)
    pts = jax.random.normal(jax.random.key(1), (50, 7, 2))
    back = jax.vmap(geometry.to_world)(poses, jax.vmap(geometry.to_local)(poses, pts))
    np.testing.assert_allclose(back, pts, atol=1e-5)
    ident = geometry.compose(poses, geometry.inverse(poses))
    np.testing.assert_allclose(ident, np.zeros_like(ident), atol=1e-5)


def test_to_local_quarter_turn():
    # A robot at (1, 2) facing +y sees a point 3 m further along +y straight ahead (robot +x).
    local = geometry.to_local(jnp.array([1.0, 2.0, math.pi / 2]), jnp.array([1.0, 5.0]))
    np.testing.assert_allclose(local, [3.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(geometry.rotate(math.pi / 2, jnp.array([1.0, 0.0])), [0, 1], atol=1e-7)


@pytest.mark.parametrize(
    ("angle", "expected"),
    [
        (0.0, HALF_L),  # front
        (math.pi, HALF_L),  # back
        (math.pi / 2, HALF_W),  # left side
        (-math.pi / 2, HALF_W),  # right side
        (math.atan2(HALF_W, HALF_L), math.hypot(HALF_L, HALF_W)),  # corner
        (math.pi / 4, HALF_W / math.sin(math.pi / 4)),  # 45 deg leaves through the side
        (math.radians(20), HALF_L / math.cos(math.radians(20))),  # 20 deg through the front
    ],
)
def test_boundary_distance_closed_form(angle, expected):
    assert float(KAIROS.boundary_distance(jnp.float32(angle))) == pytest.approx(expected, rel=1e-6)


def test_boundary_distance_720_rays_symmetric_and_bounded():
    b = np.asarray(KAIROS.boundary_distance(geometry.ray_angles()))
    assert b.shape == (720,)
    assert b.min() == pytest.approx(HALF_W) and b.max() <= math.hypot(HALF_L, HALF_W) + 1e-6
    np.testing.assert_allclose(b, b[::-1][np.r_[-1, 0:719]], rtol=1e-5)  # mirror symmetric


@pytest.mark.parametrize(
    ("angle", "range_", "expected"),
    [
        # front: cos branch, f = l - h/2
        (0.0, 2.0, 2.0 - HALF_L),
        # side: |sin| r = 0.77 >= w/2, f = l - w/2
        (math.pi / 2, 2.0, 2.0 - HALF_W),
        # 30 deg: |sin| r = 0.385 < 0.455 -> cos branch, b_r through the front face
        (math.radians(30), 2.0, (2.0 - HALF_L / math.cos(math.radians(30))) * math.cos(math.radians(30))),
        # corner (38.8 deg): |sin| r = 0.483 >= 0.455 -> sin branch
        (
            math.atan2(HALF_W, HALF_L),
            1.5,
            (1.5 - math.hypot(HALF_L, HALF_W)) * math.sin(math.atan2(HALF_W, HALF_L)),
        ),
        # touching the front face: zero
        (0.0, HALF_L, 0.0),
    ],
)
def test_inflation_distance_eq_4_13(angle, range_, expected):
    got = float(KAIROS.inflation_distance(jnp.float32(range_), jnp.float32(angle)))
    assert got == pytest.approx(expected, abs=1e-6)


def test_inflation_branch_switches_where_the_thesis_says():
    # |sin a| * 0.77 = 0.455  <=>  a = asin(0.455 / 0.77) = 36.2 deg
    switch = math.asin(HALF_W / 0.77)
    below, above = jnp.float32(switch - 1e-3), jnp.float32(switch + 1e-3)
    l = jnp.float32(2.0)
    assert float(KAIROS.inflation_distance(l, below)) == pytest.approx(
        (2.0 - float(KAIROS.boundary_distance(below))) * math.cos(switch - 1e-3), rel=1e-5
    )
    assert float(KAIROS.inflation_distance(l, above)) == pytest.approx(
        (2.0 - float(KAIROS.boundary_distance(above))) * math.sin(switch + 1e-3), rel=1e-5
    )


def test_footprint_rejects_bad_sizes():
    with pytest.raises(ValueError, match="positive"):
        Footprint(length=-1.0)
    with pytest.raises(ValueError, match="does not enclose"):
        Footprint(radius=0.5)


def test_ray_geometry_constants_at_known_rays():
    b, scale = KAIROS.ray_geometry()
    assert b.shape == scale.shape == (720,)
    assert b[0] == pytest.approx(HALF_L) and b[180] == pytest.approx(HALF_W)  # front, left side
    assert scale[0] == pytest.approx(1.0) and scale[180] == pytest.approx(1.0)
    assert scale[60] == pytest.approx(math.cos(math.radians(30)), rel=1e-5)  # 30 deg: front branch
    assert scale[90] == pytest.approx(math.sin(math.radians(45)), rel=1e-5)  # 45 deg: side branch
