"""``methd_jax.viz`` and ``python -m train.rollout``: recorded episodes, pictures, Foxglove MCAP."""

from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import export_random_policy
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from PIL import Image

import envs
import networks
from methd_jax import floors, viz
from methd_jax import robot as robot_lib
from methd_jax.control import CONTROL_DT
from methd_jax.viz.episode import OUTCOMES
from train import rollout as rollout_cli

STEPS = 80


# nav's recording runs su's code with a second user (~25 s more on CI): in the slow set
@pytest.fixture(scope="module", params=["su", pytest.param("nav", marks=pytest.mark.slow), "guide"])
def recorded(request):
    """(name, env, rollout) of each environment, the robot driven by a constant command."""
    name = request.param
    extra = {} if name == "guide" else {"lab": True, "num_rays": 180}
    env = envs.make(name, motion="sample", split="all", **extra)
    action = np.full(env.action_size, 0.4, np.float32)
    return name, env, envs.record(env, jax.random.key(1), STEPS, lambda obs: action)


def _image(path: Path) -> Image.Image:
    assert path.stat().st_size > 1000
    im = Image.open(path)
    im.load()
    return im


def test_rollout_holds_the_episode_step_by_step(recorded):
    name, env, r = recorded
    assert r.env == name and r.num_steps == STEPS + 1
    assert r.users.shape == (STEPS + 1, 1 if name == "su" else 2, 3) and r.hips.shape == r.users.shape
    assert np.allclose(np.diff(r.t[~r.done])[: STEPS // 2], CONTROL_DT)
    # once the episode ends everything stays as it was
    if r.done.any():
        end = int(np.argmax(r.done))
        assert r.done[end:].all() and np.all(r.users[end:] == r.users[end])
        assert r.outcome in OUTCOMES[1:]
    else:
        assert r.outcome == "running"
    if name == "nav":
        return  # the replay below runs the same code as su's with a second user
    # replaying the same actions by hand gives the recorded poses (up to the episode's end)
    state = env.reset(jax.random.key(1))
    step = jax.jit(env.step)
    action = np.full(env.action_size, 0.4, np.float32)
    for i in range(1, 11):
        state = step(state, action)
        w = state.pipeline_state
        assert np.allclose(r.users[i], jax.vmap(env.bank.at, (0, None))(w.users, w.t)["pose"], atol=1e-5)
        if name == "guide":
            assert r.robot is None and np.isclose(r.u_w[i], w.u_w)
        else:
            assert np.allclose(r.robot[i], robot_lib.pose(w.robot), atol=1e-5)
            assert np.allclose(r.ranges[i], state.obs[:180], atol=1e-5)


def test_lidar_hits_lie_on_the_obstacles(recorded):
    name, _, r = recorded
    if name == "guide":
        pytest.skip("GuideRL has no robot and no LiDAR")
    hits = np.concatenate([r.hits(i) for i in range(0, r.num_steps, 10)])
    assert len(hits) > 20
    floor = jax.tree.map(np.asarray, r.floor)
    sd = np.asarray(jax.vmap(lambda p: floors.signed_distance(floor, p))(hits))
    # N(0, 0.03) range noise: every return within 5 standard deviations of a surface
    assert np.abs(sd).max() < 0.15, np.abs(sd).max()


def test_frame_and_animation_are_images_of_the_requested_size(recorded, tmp_path):
    name, _, r = recorded
    png = tmp_path / f"{name}.png"
    viz.frame(r, STEPS // 2, png, size=(480, 360))
    assert _image(png).size == (480, 360)
    gif = viz.animate(r, tmp_path / f"{name}.gif", stride=20, size=(320, 300))
    im = _image(gif)
    assert im.size == (320, 300)
    # Pillow merges identical consecutive frames (a frozen, ended episode) into longer ones, so the
    # total duration is what counts: one frame per 20 steps at real time (2 fps -> 500 ms each)
    durations = []
    for k in range(im.n_frames):
        im.seek(k)
        durations.append(im.info["duration"])
    assert sum(durations) == 500 * len(range(0, STEPS + 1, 20))
    # frames differ: the users walk
    im.seek(0)
    first = np.asarray(im.convert("RGB"))
    im.seek(im.n_frames - 1)
    assert np.any(first != np.asarray(im.convert("RGB")))


def test_foxglove_mcap_reads_back_with_the_expected_channels(recorded, tmp_path):
    name, _, r = recorded
    path = viz.to_mcap(r, tmp_path / f"{name}.mcap", stride=2)
    n = len(range(0, r.num_steps, 2)) + ((r.num_steps - 1) % 2 != 0)
    users = [f"/user{j + 1}/pose" for j in range(r.num_users)]
    want = {"/floor": 1, "/scene": n, **dict.fromkeys(users, n)}
    if name != "guide":
        want |= {"/tf": n, "/scan": n, "/robot/pose": n, "/goal": n}
    counts, decoded = {}, {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        schemas = {
            c.topic: reader.get_summary().schemas[c.schema_id].name
            for c in reader.get_summary().channels.values()
        }
        for _, channel, message, proto in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            decoded.setdefault(channel.topic, []).append((message.log_time, proto))
    assert counts == want
    assert schemas["/floor"] == schemas["/scene"] == "foxglove.SceneUpdate"
    assert schemas[users[0]] == "foxglove.PoseInFrame"
    floor = decoded["/floor"][0][1].entities[0]
    assert len(floor.cylinders) == int(r.floor.circle_mask.sum())
    assert len(floor.triangles) == int(r.floor.polygon_mask.sum())
    t, pose = decoded[users[0]][3]
    assert t == round(r.t[6] * 1e9)
    assert np.allclose([pose.pose.position.x, pose.pose.position.y], r.users[6, 0, :2], atol=1e-6)
    if name != "guide":
        assert schemas["/scan"] == "foxglove.LaserScan" and schemas["/tf"] == "foxglove.FrameTransform"
        scan = decoded["/scan"][3][1]
        assert scan.frame_id == "base_link" and np.allclose(scan.ranges, r.ranges[6], atol=1e-6)
        assert np.isclose(scan.end_angle, 2 * np.pi * 179 / 180)
        ids = {e.id for e in decoded["/scene"][0][1].entities}
        assert {"robot", "goal", "user1", "status"} <= ids


def test_polar_scan_and_user_weight_plots(recorded, tmp_path):
    name, _, r = recorded
    if name == "su":
        with pytest.raises(ValueError, match="no user weight"):
            viz.user_weight(r)
        viz.polar_scan(r.ranges[5], max_range=r.lidar_range, path=tmp_path / "scan.png")
        assert _image(tmp_path / "scan.png").size == (450, 450)
    elif name == "guide":
        viz.user_weight(r, path=tmp_path / "u_w.png")
        assert _image(tmp_path / "u_w.png").size[0] > 400


def test_bad_requests_are_refused_with_a_reason(tmp_path):
    env = envs.make("guide", motion="sample", split="all")
    r = envs.record(env, jax.random.key(0), 5)
    with pytest.raises(IndexError, match="outside the rollout's 6 steps"):
        viz.frame(r, 6)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        viz.animate(r, tmp_path / "a.avi")
    with pytest.raises(ValueError, match="steps must be at least 1"):
        envs.record(env, jax.random.key(0), 0)
    with pytest.raises(ValueError, match="one scan"):
        viz.polar_scan(np.ones((2, 3)))


def test_rollout_cli_writes_every_picture_for_a_policy(tmp_path, capsys):
    env = envs.make("su", motion="sample", split="all", num_rays=72)
    run = tmp_path / "run"
    export_random_policy(run, env, "su", networks.ActorCritic(num_rays=72, hidden=(32, 32)), seed=0)
    out = tmp_path / "out"
    code = rollout_cli.main([str(run), "lab=true", "--steps", "60", "--stride", "10", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "su: " in text and "steps recorded" in text
    for name in ("frame.png", "scan.png", "rollout.gif", "rollout.mcap"):
        assert (out / name).stat().st_size > 1000, name
    assert not (out / "u_w.png").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env", "guide", "lab=true"], "unknown option 'lab'"),
        (["--env", "su", "lab=maybe"], "lab expects true or false"),
        (["/nonexistent/run"], "holds no exported policy"),
        (["--steps", "0"], "--steps and --stride must be at least 1"),
    ],
)
def test_rollout_cli_bad_input_is_one_line(args, message, capsys, tmp_path):
    try:
        code = rollout_cli.main([*args, "--out", str(tmp_path)])
    except SystemExit as exit:
        code = exit.code
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err


def test_readme_shows_a_committed_rollout_animation():
    root = Path(__file__).resolve().parents[1]
    assert "](docs/rollout.gif)" in (root / "README.md").read_text()
    im = _image(root / "docs" / "rollout.gif")
    assert im.format == "GIF" and im.n_frames > 20 and im.size == (600, 600)
