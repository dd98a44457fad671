import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from methd_jax import floors, lidar
from methd_jax.floors import Floor, FloorConfig, FloorSpecError

SQUARE = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]


def test_from_primitives_pads_and_orients():
    cw_triangle = [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0)]
    f = Floor.from_primitives(
        circles=[(2.0, 2.0, 0.5)], polygons=[SQUARE, cw_triangle], max_circles=3, max_vertices=5
    )
    assert f.capacity == (3, 2, 5)
    assert f.circle_mask.tolist() == [True, False, False]
    assert f.vertex_mask.tolist() == [[True] * 4 + [False], [True] * 3 + [False] * 2]
    tri = np.asarray(f.polygons[1])
    # stored counter-clockwise, padded by repeating the last vertex
    area2 = np.sum(tri[:3, 0] * np.roll(tri[:3, 1], -1) - np.roll(tri[:3, 0], -1) * tri[:3, 1])
    assert area2 > 0
    np.testing.assert_array_equal(tri[3], tri[2])
    np.testing.assert_array_equal(tri[4], tri[2])
    circles, polygons = f.primitives()
    assert circles == [(2.0, 2.0, 0.5)]
    assert [len(p) for p in polygons] == [4, 3]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"polygons": [SQUARE, [(0, 0), (2, 0), (1, 0.2), (2, 2), (0, 2)]]}, "polygon 1 is not convex"),
        ({"polygons": [[(0, 0), (1, 1), (2, 2)]]}, "polygon 0 is degenerate: it has zero area"),
        ({"polygons": [[(0, 0), (1, 0), (1, 0), (0, 1)]]}, "polygon 0 is degenerate: vertices 1 and 2"),
        ({"polygons": [SQUARE, SQUARE, [(0, 0), (float("nan"), 0), (1, 1)]]}, "polygon 2 has a non-finite"),
        ({"circles": [(0, 0, 1), (float("nan"), 1, 1)]}, "circle 1 has a non-finite"),
        ({"circles": [(0, 0, -1)]}, "circle 0 has a non-positive radius"),
        ({"circles": [(0, 0)]}, r"circle 0 must be \(x, y, r\)"),
        ({"polygons": [[(0, 0), (1, 0)]]}, "polygon 0 has 2 vertices"),
        ({"circles": [(0, 0, 1)] * 3, "max_circles": 2}, "3 circles exceed the capacity of 2 .circle 2"),
        ({"polygons": [SQUARE] * 2, "max_polygons": 1}, "2 polygons exceed the capacity of 1 .polygon 1"),
        ({"polygons": [SQUARE], "max_vertices": 3}, "polygon 0 has 4 vertices, more than the capacity"),
    ],
)
def test_bad_floor_specs_are_rejected_by_name(kwargs, message):
    with pytest.raises(FloorSpecError, match=message):
        Floor.from_primitives(**kwargs)


def test_pentagram_is_not_convex():
    star = [(np.cos(a), np.sin(a)) for a in np.pi / 2 + 4 * np.pi / 5 * np.arange(5)]
    with pytest.raises(FloorSpecError, match="polygon 0 is not convex"):
        Floor.from_primitives(polygons=[star])


def test_empty_floor_needs_bounds():
    with pytest.raises(FloorSpecError, match="bounds"):
        Floor.from_primitives()
    f = Floor.from_primitives(bounds=(-1, -1, 1, 1))
    assert np.isinf(np.asarray(lidar.scan(f, jnp.zeros(3)))).all()


def test_generate_keeps_obstacles_inside_the_walls():
    cfg = FloorConfig()
    batch = floors.generate_batch(jax.random.key(0), 256, cfg)
    b = np.asarray(batch.bounds)[:, None, :]
    c = np.asarray(batch.circles)
    assert np.all(c[..., 0] - c[..., 2] >= b[..., 0] - 1e-5) and np.all(
        c[..., 0] + c[..., 2] <= b[..., 2] + 1e-5
    )
    assert np.all(c[..., 1] - c[..., 2] >= b[..., 1] - 1e-5) and np.all(
        c[..., 1] + c[..., 2] <= b[..., 3] + 1e-5
    )
    inner = np.asarray(batch.polygons)[:, : cfg.num_polygons[1]]  # the last 4 polygons are walls
    lo, hi = np.asarray(batch.bounds)[:, None, None, :2], np.asarray(batch.bounds)[:, None, None, 2:]
    assert np.all(inner >= lo - 1e-5) and np.all(inner <= hi + 1e-5)
    sizes = np.asarray(batch.bounds)[:, 2:] - np.asarray(batch.bounds)[:, :2]
    assert sizes.min() >= cfg.room_size[0] - 1e-4 and sizes.max() <= cfg.room_size[1] + 1e-4


def test_generated_polygons_are_valid_convex_polygons():
    batch = floors.generate_batch(jax.random.key(1), 32)
    for i in range(32):
        f = jax.tree.map(lambda x, i=i: x[i], batch)
        circles, polygons = f.primitives()
        assert len(circles) == 12 and len(polygons) == 16
        Floor.from_primitives(circles, polygons)  # re-validates every obstacle on the host


def test_generate_masks_follow_the_configured_counts_and_hide_obstacles():
    cfg = FloorConfig(num_circles=(2, 6), num_polygons=(0, 5))
    batch = floors.generate_batch(jax.random.key(2), 300, cfg)
    assert batch.circles.shape == (300, 6, 3) and batch.polygons.shape == (300, 9, 4, 2)
    n_c = np.asarray(batch.circle_mask).sum(1)
    n_p = np.asarray(batch.polygon_mask[:, :5]).sum(1)
    assert n_c.min() == 2 and n_c.max() == 6 and n_p.min() == 0 and n_p.max() == 5
    assert np.all(np.asarray(batch.polygon_mask[:, 5:]))  # walls always present
    # A masked-out circle is invisible to the LiDAR: unmask it and the scan changes.
    i = int(np.argmin(n_c))
    f = jax.tree.map(lambda x: x[i], batch)
    shown = f.replace(circle_mask=jnp.ones_like(f.circle_mask))
    pose = jnp.array([*np.asarray(f.bounds[:2]) + 0.3, 0.0])
    assert not np.allclose(lidar.scan(f, pose), lidar.scan(shown, pose))


def test_distinct_keys_give_distinct_floors():
    batch = floors.generate_batch(jax.random.key(3), 64)
    flat = np.asarray(batch.circles).reshape(64, -1)
    assert len({row.tobytes() for row in flat}) == 64
    again = floors.generate_batch(jax.random.key(3), 64)
    np.testing.assert_array_equal(np.asarray(again.polygons), np.asarray(batch.polygons))


def test_thousands_of_floors_in_one_jitted_call():
    batch = floors.generate_batch(jax.random.key(4), 4096)
    assert batch.polygons.shape == (4096, 16, 4, 2)
    assert np.isfinite(np.asarray(batch.polygons)).all()


def test_floor_config_rejects_nonsense():
    with pytest.raises(ValueError, match="room_size"):
        FloorConfig(room_size=(10.0, 5.0))
    with pytest.raises(ValueError, match="num_circles"):
        FloorConfig(num_circles=(-1, 3))
    with pytest.raises(ValueError, match="do not fit"):
        FloorConfig(room_size=(2.0, 3.0), box_side=(0.5, 2.0))


def test_lab_asset_loads():
    f = floors.lab()
    np.testing.assert_allclose(np.asarray(f.bounds), [-5.5, -6.5, 5.5, 6.5])
    circles, polygons = f.primitives()
    spec = json.loads(floors.LAB_ASSET.read_text())
    assert len(circles) + len(polygons) == len(spec["obstacles"]) + 4  # + walls
    # From the middle of the room every ray ends at an obstacle or a wall within the room.
    r = np.asarray(lidar.scan(f, jnp.array([0.0, -2.0, 0.3])))
    assert np.isfinite(r).all() and r.max() <= np.hypot(11, 13)
    assert bool(floors.is_free(f, jnp.array([0.0, -2.0]), 0.77))
    padded = f.pad(12, 16, 4)
    assert padded.capacity == (12, 16, 4)
    np.testing.assert_allclose(lidar.scan(padded, jnp.array([0.0, -2.0, 0.3])), r, rtol=1e-6)


def test_lab_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(FloorSpecError, match=r"nope\.json: lab floor asset not found"):
        floors.lab(missing)
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps(
            {"size": [5, 5], "wall_thickness": 0.2, "obstacles": [{"polygon": [[0, 0], [1, 1], [2, 2]]}]}
        )
    )
    with pytest.raises(FloorSpecError, match=r"bad\.json: polygon 0 is degenerate"):
        floors.lab(bad)
    (tmp_path / "junk.json").write_text("{")
    with pytest.raises(FloorSpecError, match=r"junk\.json: not valid JSON"):
        floors.lab(tmp_path / "junk.json")


def test_signed_distance_on_known_shapes():
    f = Floor.from_primitives(circles=[(5.0, 0.0, 1.0)], polygons=[SQUARE])
    sd = lambda x, y: float(floors.signed_distance(f, jnp.array([x, y])))  # noqa: E731
    assert sd(5.0, 3.0) == pytest.approx(2.0)  # above the circle
    assert sd(5.0, 0.5) == pytest.approx(-0.5)  # inside the circle
    assert sd(0.5, -2.0) == pytest.approx(2.0)  # below the square's bottom edge
    assert sd(-3.0, 5.0) == pytest.approx(5.0)  # from the square's corner (0, 1): (3, 4)
    assert sd(0.5, 0.6) == pytest.approx(-0.4)  # inside the square, 0.4 from the top edge


def test_free_space_query_agrees_with_the_ray_caster():
    batch = floors.generate_batch(jax.random.key(5), 64)
    pts = jax.random.uniform(jax.random.key(6), (64, 50, 2), minval=-7.0, maxval=7.0)
    sd = jax.vmap(jax.vmap(floors.signed_distance, (None, 0)), (0, 0))(batch, pts)
    free = jax.vmap(jax.vmap(floors.is_free, (None, 0, None)), (0, 0, None))(batch, pts, 0.77)
    poses = jnp.concatenate([pts, jnp.zeros((64, 50, 1))], -1)

    def nearest_ray(num_rays):
        scan = lambda f, p: lidar.scan(f, p, num_rays=num_rays)  # noqa: E731
        return np.asarray(jax.vmap(jax.vmap(scan, (None, 0)), (0, 0))(batch, poses).min(-1))

    nearest = nearest_ray(720)
    sd, free = np.asarray(sd), np.asarray(free)
    assert free.sum() > 200  # the check below is exercised
    # A clear disc has no ray shorter than its radius ...
    assert np.all(nearest[free] >= 0.77 - 1e-5)
    # ... no ray is shorter than the clearance ...
    outside = sd > 0
    assert np.all(nearest[outside] >= sd[outside] - 1e-4)
    # ... and with fine rays the shortest ray is the clearance. (At 720 rays a ray may pass a
    # polygon corner that points at the sensor and land up to ~2 cm further; that gap shrinks
    # with the ray spacing, which is what this checks.)
    fine = nearest_ray(720 * 8)
    assert np.all(fine[outside] >= sd[outside] - 1e-4)
    assert np.all(fine[outside] <= sd[outside] + 5e-3)
    # Inside an obstacle every query says blocked and the sensor reads 0 somewhere.
    assert not free[~outside].any() and np.all(nearest[~outside] == 0)


def test_push_clear_finds_the_nearest_clear_point_next_to_one_obstacle():
    f = Floor.from_primitives(
        circles=[(0.0, 0.0, 1.0)], polygons=[[(4, -1), (6, -1), (6, 1), (4, 1)]], bounds=(-10, -10, 10, 10)
    )
    # brute force: the nearest point of a fine grid whose 0.9 m disc is clear
    g = np.stack(np.meshgrid(np.linspace(-4, 9, 521), np.linspace(-4, 4, 321)), -1).reshape(-1, 2)
    free = np.asarray(jax.vmap(lambda p: floors.is_free(f, p, 0.9))(jnp.asarray(g)))
    starts = [(0.3, 0.2), (-0.5, -0.1), (1.2, 0.0), (4.5, 0.3), (5.9, -0.8), (3.5, 0.5), (7.0, 1.5)]
    for x in starts:
        got = np.asarray(floors.push_clear(f, jnp.asarray(x), 0.9))
        nearest = g[free][np.argmin(np.linalg.norm(g[free] - x, axis=1))]
        assert np.linalg.norm(got - x) == pytest.approx(np.linalg.norm(nearest - x), abs=0.03), x
        assert float(floors.clearance(f, jnp.asarray(got))) >= 0.9 - 1e-4
    # a clear point stays put, and a point pushed away from a user keeps its distance
    assert np.asarray(floors.push_clear(f, jnp.array([-3.0, 3.0]), 0.9)).tolist() == [-3.0, 3.0]
    got = floors.push_clear(f, jnp.array([-3.0, 3.0]), 0.9, avoid=jnp.array([[-3.5, 3.0]]), avoid_radius=1.77)
    assert float(jnp.linalg.norm(got - jnp.array([-3.5, 3.0]))) == pytest.approx(1.77, abs=1e-4)
    # the edge of the bounds counts as an obstacle
    assert float(floors.push_clear(f, jnp.array([9.8, -5.0]), 0.9)[0]) == pytest.approx(9.1, abs=1e-4)
    # a point exactly on a wall's face that is also the bound (where the distance has no
    # derivative: autodiff gave NaN there) still moves into the room
    wall = Floor.from_primitives(
        polygons=[[(5.5, -7), (6, -7), (6, 7), (5.5, 7)]], bounds=(-5.5, -6.5, 5.5, 6.5)
    )
    got = np.asarray(floors.push_clear(wall, jnp.array([5.5, 0.0]), 0.9))
    np.testing.assert_allclose(got, [4.6, 0.0], atol=1e-3)


def test_push_clear_frees_most_blocked_points_on_cluttered_floors():
    # the environments' floors (13 x 16 m, up to 8 + 8 obstacles): about half the area is too
    # tight for a 0.9 m disc, and gaps narrower than the disc cannot free every point
    cfg = FloorConfig(room_size=(13.0, 16.0))
    batch = floors.generate_batch(jax.random.key(11), 32, cfg)
    pts = jax.random.uniform(jax.random.key(12), (32, 40, 2), minval=-6.0, maxval=6.0)
    clear = jax.vmap(jax.vmap(floors.clearance, (None, 0)), (0, 0))
    pushed = jax.vmap(jax.vmap(lambda f, p: floors.push_clear(f, p, 0.9), (None, 0)), (0, 0))(batch, pts)
    before, after = np.asarray(clear(batch, pts)), np.asarray(clear(batch, pushed))
    blocked = before < 0.9
    assert blocked.sum() > 400
    assert np.all(after[~blocked] == before[~blocked])  # clear points do not move
    assert np.mean(after[blocked] >= 0.9 - 1e-3) > 0.8  # most blocked ones end clear
    assert np.mean(after[blocked] >= 0.77) > 0.9  # and the footprint fits at nearly all
    assert np.mean(after[blocked] >= np.minimum(before[blocked], 0.9) - 1e-3) > 0.97


def test_mjcf_export_uses_the_right_geoms():
    batch = floors.generate_batch(jax.random.key(7), 8, FloorConfig(triangle_fraction=0.5))
    f = jax.tree.map(lambda x: x[0], batch)
    m = mujoco.MjModel.from_xml_string(floors.to_mjcf(f))
    types = [mujoco.mjtGeom(t).name for t in m.geom_type]
    _, polygons = f.primitives()
    n_tri = sum(len(p) == 3 for p in polygons)
    assert types.count("mjGEOM_CYLINDER") == 12
    assert types.count("mjGEOM_MESH") == n_tri and n_tri > 0
    assert types.count("mjGEOM_BOX") == 16 - n_tri
    assert m.nmat >= 1  # mjx.ray needs a material
    caps = mujoco.MjModel.from_xml_string(floors.to_mjcf(f, circle_geom="capsule"))
    assert [mujoco.mjtGeom(t).name for t in caps.geom_type].count("mjGEOM_CAPSULE") == 12
    with pytest.raises(ValueError, match="circle_geom"):
        floors.to_mjcf(f, circle_geom="sphere")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"obstacles": "none"}, "obstacles must be a list"),
        ({"wall_thickness": -0.2}, "wall_thickness must be in"),
        ({"size": "11x13"}, "size must be two side lengths"),
        ({"size": [1e9, 13.0]}, "size must be two side lengths"),
    ],
)
def test_a_floor_file_that_would_load_wrong_is_refused(tmp_path, change, message):
    spec = json.loads(floors.LAB_ASSET.read_text())
    path = tmp_path / "floor.json"
    path.write_text(json.dumps({**spec, **change}))
    with pytest.raises(floors.FloorSpecError, match=message) as err:
        floors.lab(path)
    assert str(err.value).startswith(str(path))


@pytest.mark.parametrize("which", ["lab", "procedural"])
def test_obstacle_discs_cover_every_obstacle_and_leave_the_walls_out(which):
    if which == "lab":
        floor = floors.lab()
    else:
        cfg = floors.FloorConfig(room_size=(13.0, 16.0), num_circles=(8, 8), num_polygons=(8, 8))
        floor = floors.generate(jax.random.key(5), cfg)
    discs, mask = (np.asarray(x) for x in floors.obstacle_discs(floor, 0.0))
    discs = discs[mask]
    b = np.asarray(floor.bounds)
    pts = np.random.default_rng(0).uniform(b[:2] - 0.2, b[2:] + 0.2, (40_000, 2))
    sd = np.asarray(jax.vmap(lambda p: floors.signed_distance(floor, p))(jnp.asarray(pts, jnp.float32)))
    in_room = np.all((pts > b[:2]) & (pts < b[2:]), 1)
    covered = np.any(
        np.linalg.norm(pts[:, None] - discs[None, :, :2], axis=-1) <= discs[None, :, 2] + 1e-5, 1
    )
    assert np.sum(in_room & (sd < 0)) > 500
    assert np.all(covered[in_room & (sd < 0)])  # every point of furniture is inside a disc
    # no disc for a wall: every centre is inside the room and none spans half of it
    assert np.all((discs[:, :2] > b[:2]) & (discs[:, :2] < b[2:])) and discs[:, 2].max() < 1.5
    assert np.mean(covered[in_room]) < 2.5 * np.mean(in_room & (sd < 0)) / np.mean(in_room)  # not much more
    widened = np.asarray(floors.obstacle_discs(floor, 0.45)[0])[mask]
    np.testing.assert_allclose(widened[:, 2], discs[:, 2] + 0.45, rtol=1e-6)
