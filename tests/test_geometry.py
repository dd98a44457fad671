import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methd_jax import geometry
from methd_jax.geometry import KAIROS, Footprint, path_around_discs

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


def _shortest_way_round(a, b, centre, radius, samples=1500):
    """Independent reference: the straight segment if it misses the disc, else the shortest of
    (a -> p_i) + arc(p_i, p_j) + (p_j -> b) over sampled rim points p_i, p_j that a and b can see."""
    a, b, centre = (np.asarray(v, np.float64) - centre for v in (a, b, centre))
    ab = b - a
    t = np.clip(-np.dot(a, ab) / np.dot(ab, ab), 0.0, 1.0)
    if np.linalg.norm(a + t * ab) >= radius:
        return float(np.linalg.norm(ab))
    ang = np.linspace(-np.pi, np.pi, samples, endpoint=False)
    rim = radius * np.stack([np.cos(ang), np.sin(ang)], 1)
    sees_a = np.sum(rim * (a - rim), 1) >= 0  # the tangent plane at p does not hide a
    sees_b = np.sum(rim * (b - rim), 1) >= 0
    arc = radius * np.abs(np.angle(np.exp(1j * (ang[None, :] - ang[:, None]))))
    total = np.linalg.norm(rim - a, axis=1)[:, None] + arc + np.linalg.norm(rim - b, axis=1)[None, :]
    return float(np.min(np.where(sees_a[:, None] & sees_b[None, :], total, np.inf)))


def test_the_way_round_a_disc_matches_a_sampled_shortest_path():
    rng = np.random.default_rng(0)
    disc = jnp.array([[0.4, -0.2, 1.3]])
    checked = blocked = 0
    while checked < 40:
        a, b = rng.uniform(-4, 4, (2, 2))
        if min(np.linalg.norm(a - [0.4, -0.2]), np.linalg.norm(b - [0.4, -0.2])) < 1.35:
            continue
        ours = float(path_around_discs(jnp.asarray(a), jnp.asarray(b), disc, jnp.array([True])))
        ref = _shortest_way_round(a, b, np.array([0.4, -0.2]), 1.3)
        assert ours == pytest.approx(ref, abs=2e-3)
        blocked += ours > np.linalg.norm(b - a) + 1e-3
        checked += 1
    assert blocked >= 10  # both kinds of segment were checked


def test_the_way_round_discs_counts_only_what_is_in_the_way():
    f = lambda *v: jnp.asarray(v, jnp.float32)  # noqa: E731
    disc, on = jnp.array([[0.0, 0.0, 1.0]]), jnp.array([True])
    through = 2 * math.sqrt(3) + math.pi / 3  # tangent, 60 degrees of rim, tangent
    assert float(path_around_discs(f(-2, 0), f(2, 0), disc, on)) == pytest.approx(through, rel=1e-5)
    assert float(path_around_discs(f(-2, 1.5), f(2, 1.5), disc, on)) == pytest.approx(4.0)  # clear
    assert float(path_around_discs(f(-2, 0), f(2, 0), disc, jnp.array([False]))) == pytest.approx(4.0)
    assert float(path_around_discs(f(-2, 0), f(0.5, 0), disc, on)) == pytest.approx(2.5)  # goal inside
    # a start inside the disc counts from the rim: out, round and on
    inside = math.sqrt(3) + 2 * math.pi / 3
    assert float(path_around_discs(f(-0.5, 0), f(2, 0), disc, on)) == pytest.approx(inside, rel=1e-5)
    # two discs on the line: each adds its own way round
    two = jnp.array([[0.0, 0.0, 1.0], [6.0, 0.0, 1.0]])
    got = float(path_around_discs(f(-2, 0), f(8, 0), two, jnp.array([True, True])))
    one = math.sqrt(3) + math.sqrt(63) + (2 * math.pi / 3 - math.acos(1 / 8)) - 10.0  # from 2 m to 8 m
    assert got == pytest.approx(10.0 + 2 * one, rel=1e-5)
    # continuous: approaching the goal round the disc, the length shrinks to zero
    ts = np.linspace(0, 1, 50)
    lengths = [
        float(path_around_discs(f(2 * math.cos(t * 3), 2 * math.sin(t * 3)), f(2, 0), disc, on)) for t in ts
    ]
    assert np.all(np.abs(np.diff(lengths)) < 0.2) and lengths[0] == pytest.approx(0.0, abs=1e-5)
