import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import mujoco_scan, mujoco_scan_model

from methd_jax import floors, lidar
from methd_jax.floors import Floor, FloorConfig


def _free_poses(floor, rng, n, clearance=0.05):
    b = np.asarray(floor.bounds)
    out = []
    while len(out) < n:
        xy = rng.uniform(b[:2] - 1.0, b[2:] + 1.0)  # some poses outside the room: misses
        if float(floors.signed_distance(floor, jnp.asarray(xy, jnp.float32))) > clearance:
            out.append([*xy, rng.uniform(-math.pi, math.pi)])
    return np.asarray(out, np.float32)


@pytest.mark.parametrize(
    ("cfg", "n_floors", "seed"),
    [
        (FloorConfig(), 160, 0),  # walls, boxes and triangles (triangles become meshes)
        (FloorConfig(wall_thickness=0.0, num_circles=(4, 12), num_polygons=(4, 12)), 60, 1),
    ],
    ids=["walled", "open"],
)
def test_scan_matches_mujoco_mj_ray(cfg, n_floors, seed):
    """Every ray within 1e-4 m of MuJoCo's float64 caster where either hits within 30 m."""
    batch = floors.generate_batch(jax.random.key(seed), n_floors, cfg)
    rng = np.random.default_rng(seed)
    singles = [jax.tree.map(lambda x, i=i: x[i], batch) for i in range(n_floors)]
    poses = np.stack([_free_poses(f, rng, 4) for f in singles])
    ours = np.asarray(jax.jit(jax.vmap(jax.vmap(lidar.scan, (None, 0))))(batch, jnp.asarray(poses)))
    hits = misses = 0
    for i, f in enumerate(singles):
        m = mujoco.MjModel.from_xml_string(floors.to_mjcf(f))
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        for j in range(poses.shape[1]):
            ref = mujoco_scan_model(m, d, poses[i, j])
            got = ours[i, j]
            either = np.minimum(got, ref) <= 30.0
            err = np.abs(np.minimum(got, 30.0) - np.minimum(ref, 30.0))
            assert np.all(err[either] <= 1e-4), (
                f"floor {i} pose {poses[i, j]}: ray {np.argmax(err)} ours {got[np.argmax(err)]} "
                f"mj_ray {ref[np.argmax(err)]}"
            )
            assert np.array_equal(np.isinf(got), np.isinf(ref)), f"floor {i}: hit/miss disagree"
            hits += either.sum()
            misses += (~either).sum()
    assert hits + misses == n_floors * 4 * 720
    assert hits > 50_000
    if not cfg.has_walls:
        assert misses > 50_000  # misses were exercised


def test_ray_convention_and_known_room():
    f = Floor.from_primitives(
        polygons=[p.tolist() for p in np.asarray(floors.walls(jnp.array([-5.0, -5.0, 5.0, 5.0]), 0.2))]
    )
    r = np.asarray(lidar.scan(f, jnp.zeros(3)))
    assert r.shape == (720,)
    assert r[0] == pytest.approx(5.0) and r[180] == pytest.approx(5.0)  # +x wall, +y wall
    assert r[90] == pytest.approx(5.0 * math.sqrt(2), rel=1e-5)  # 45 deg: the corner
    # ray i points at yaw + 2 pi i / 720: a robot facing +y sees a pillar at (0, 3) on ray 0,
    # and one at (-3, 0) (its left) on ray 180.
    g = Floor.from_primitives(circles=[(0.0, 3.0, 0.5), (-3.0, 0.0, 0.25)])
    s = np.asarray(lidar.scan(g, jnp.array([0.0, 0.0, math.pi / 2])))
    assert s[0] == pytest.approx(2.5) and s[180] == pytest.approx(2.75)
    assert np.isinf(s[360]) and np.isinf(s[540])


def test_inside_an_obstacle_reads_zero_and_max_range_clamps():
    f = Floor.from_primitives(circles=[(0.0, 0.0, 1.0)], polygons=[[(3, -1), (4, -1), (4, 1), (3, 1)]])
    assert np.all(np.asarray(lidar.scan(f, jnp.zeros(3))) == 0.0)
    assert np.all(np.asarray(lidar.scan(f, jnp.array([3.5, 0.0, 0.0]))) == 0.0)
    far = np.asarray(lidar.scan(f, jnp.array([-3.0, 0.0, 0.0]), max_range=3.0))
    assert far.max() == 3.0 and far[0] == pytest.approx(2.0)


def test_extra_circles_are_seen_like_floor_circles():
    batch = floors.generate_batch(jax.random.key(2), 1)
    f = jax.tree.map(lambda x: x[0], batch)
    users = jnp.array([[1.0, 0.5, 0.25], [-2.0, 1.0, 0.25]])
    pose = jnp.array([0.0, 0.0, 0.3])
    if float(floors.signed_distance(f, pose[:2])) < 0.1:
        pose = pose.at[:2].set(jnp.array([0.0, -1.0]))
    circles, polygons = f.primitives()
    merged = Floor.from_primitives(
        circles + [tuple(map(float, u)) for u in users], polygons, bounds=np.asarray(f.bounds)
    )
    np.testing.assert_allclose(lidar.scan(f, pose, extra_circles=users), lidar.scan(merged, pose), rtol=1e-6)
    hidden = lidar.scan(f, pose, extra_circles=users, extra_mask=jnp.array([False, False]))
    np.testing.assert_allclose(hidden, lidar.scan(f, pose), rtol=1e-6)


def _hits_flat_face_away_from_corners(floor, pose, ranges, margin=0.05, min_incidence=0.3):
    """Rays that end on a polygon edge at least ``margin`` from its ends, not grazing it."""
    pose = np.asarray(pose, np.float64)
    ang = pose[2] + 2 * np.pi * np.arange(len(ranges)) / len(ranges)
    d = np.stack([np.cos(ang), np.sin(ang)], 1)
    hit = pose[:2] + ranges[:, None] * d
    _, polygons = floor.primitives()
    good = np.zeros(len(ranges), bool)
    for p in polygons:
        p = np.asarray(p, np.float64)
        for a, b in zip(p, np.roll(p, -1, 0), strict=True):
            e = b - a
            L = np.linalg.norm(e)
            u = e / L
            n = np.array([u[1], -u[0]])
            s = (hit - a) @ u
            on = np.abs((hit - a) @ n) < 1e-4
            inner = (s > margin) & (s < L - margin)
            steep = np.abs(d @ n) > min_incidence
            good |= on & inner & steep
    return good


def test_gradient_matches_finite_differences_on_flat_faces():
    with jax.enable_x64(True):
        f = Floor.from_primitives(
            circles=[(-3.0, 2.0, 0.6)],
            polygons=[[(2, -1), (3, -1.5), (3.5, 1), (2.2, 1.2)], [(-1, -4), (1, -3), (-2, -3)]]
            + [p.tolist() for p in np.asarray(floors.walls(jnp.array([-6.0, -6.0, 6.0, 6.0]), 0.2))],
        )
        f = jax.tree.map(lambda x: x.astype(jnp.float64) if x.dtype == jnp.float32 else x, f)
        pose = jnp.array([0.3, -0.4, 0.7], jnp.float64)
        ranges = np.asarray(lidar.scan(f, pose))
        rays = np.flatnonzero(_hits_flat_face_away_from_corners(f, pose, ranges))
        assert len(rays) > 400
        jac = np.asarray(jax.jacrev(lambda p: lidar.scan(f, p))(pose))  # (720, 3)
        assert np.all(np.isfinite(jac))
        eps = 1e-6
        fd = np.stack(
            [
                (np.asarray(lidar.scan(f, pose + eps * e)) - np.asarray(lidar.scan(f, pose - eps * e)))
                / (2 * eps)
                for e in np.eye(3)
            ],
            1,
        )
        np.testing.assert_allclose(jac[rays], fd[rays], rtol=1e-5, atol=1e-6)
        # the derivative is not trivially zero: moving towards a face shortens its ray
        assert np.abs(jac[rays]).max() > 1.0


def test_gradient_is_finite_in_float32_on_generated_floors():
    batch = floors.generate_batch(jax.random.key(9), 16)
    poses = jnp.stack([jnp.zeros(16), jnp.zeros(16), jnp.linspace(-3, 3, 16)], 1)
    g = jax.vmap(jax.grad(lambda f, p: jnp.sum(jnp.minimum(lidar.scan(f, p), 30.0)), argnums=1))(batch, poses)
    assert np.all(np.isfinite(np.asarray(g)))


def test_corrupt_matches_the_thesis_sensor_model():
    ranges = jnp.concatenate([jnp.full((200_000,), 1.5), jnp.full((100_000,), 7.0)])
    out = np.asarray(lidar.corrupt(jax.random.key(0), ranges))
    assert out.min() >= 0.0 and out.max() <= 3.0
    near = out[:200_000]
    dropped = near == 3.0
    # dropout p = 0.005 per ray: 1000 expected of 200000, binomial sd ~ 31.5
    assert 850 < dropped.sum() < 1150
    noise = near[~dropped] - 1.5
    assert abs(noise.mean()) < 1e-3 and noise.std() == pytest.approx(0.03, rel=0.02)
    assert np.all(out[200_000:] <= 3.0) and np.mean(out[200_000:] == 3.0) > 0.4  # far rays clamp
    again = np.asarray(lidar.corrupt(jax.random.key(0), ranges))
    other = np.asarray(lidar.corrupt(jax.random.key(1), ranges))
    np.testing.assert_array_equal(out, again)
    assert not np.array_equal(out, other)


def test_scan_batches_over_thousands_of_floors():
    batch = floors.generate_batch(jax.random.key(10), 4096)
    poses = jnp.zeros((4096, 3))
    ranges = jax.jit(jax.vmap(lidar.scan))(batch, poses)
    assert ranges.shape == (4096, 720)
    # the room centre may fall inside an obstacle (reads 0); elsewhere walls bound every ray
    assert np.isfinite(np.asarray(ranges)).all()


def test_mujoco_helper_is_an_independent_reference():
    f = Floor.from_primitives(circles=[(2.0, 0.0, 0.5)])
    ref = mujoco_scan(f, [0.0, 0.0, 0.0])
    assert ref[0] == pytest.approx(1.5) and np.isinf(ref[360])
