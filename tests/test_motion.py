import itertools
import json
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import fuzz
from mcap_ros2.writer import Writer

from methd_jax import floors, motion
from methd_jax.motion import bags, stats
from methd_jax.motion.trajectory import (
    MotionDataError,
    TrackingGlitchWarning,
    Trajectory,
    quat_from_yaw_pitch,
    yaw_from_quat,
)

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def default_set():
    """The default synthetic set (442 trajectories, seed 0), made in memory."""
    return motion.synthesize(442, 0)


def _same(a, b):
    assert a.name == b.name and a.start_ns == b.start_ns
    np.testing.assert_array_equal(a.time, b.time)
    np.testing.assert_allclose(a.head, b.head, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.wrist, b.wrist, rtol=0, atol=1e-12)
    assert a.request_time == b.request_time


def test_round_trip_synthesise_save_load(tmp_path):
    trajs = motion.synthesize(3, 5)
    files = motion.save(tmp_path / "set", trajs)
    assert [f.name for f in files] == ["traj_0000.mcap", "traj_0001.mcap", "traj_0002.mcap"]
    for a, b in zip(trajs, motion.load(tmp_path / "set"), strict=True):
        _same(a, b)
    (one,) = motion.load(files[1])
    _same(trajs[1], one)


def test_default_set_matches_the_thesis_statistics(default_set):
    st = stats.compute(default_set)
    assert stats.check(st) == [], stats.report(st)
    assert st["trajectories"] == 442 and st["speed_mps"]["max"] <= 1.9


def test_every_trajectory_decelerates_into_the_stop_and_raises_the_arm(default_set):
    for t in default_set:
        f = motion.user_features(t)
        r = int(f["request_step"])
        speed = np.linalg.norm(f["vel_world"][:, :2], axis=1)
        walking = np.flatnonzero(speed[:r] > 0.3)
        assert walking.size, f"{t.name}: never walks"
        last = walking[-1]  # the last step faster than 0.3 m/s before the request
        # deceleration: speed falls steadily from walking pace to standing, and the user stands
        # still (not merely slows) before the request
        before = speed[max(0, last - 25) : last + 1]
        assert before.max() >= 0.3 and speed[last:r].min() < 0.05, t.name
        acc_along = np.sum(
            f["acc_world"][last - 5 : last + 5, :2] * f["vel_world"][last - 5 : last + 5, :2], 1
        )
        assert np.mean(acc_along) < 0, f"{t.name}: not decelerating when it stops"
        # arm raise: the wrist rises by at least 0.3 m over the last 1.5 s before the request
        wh = f["wrist_height"]
        assert wh[r] - wh[max(0, r - 75)] >= 0.3, t.name
        assert wh[r] > -0.45, t.name


def test_trajectories_are_consecutive_deterministic_and_clear_of_obstacles(default_set):
    for a, b in itertools.pairwise(default_set):
        assert np.linalg.norm(a.head[-1, :2] - b.head[0, :2]) < 0.02
        assert b.start_ns > a.start_ns + int(a.time[-1] * 1e9)
    again = motion.synthesize(5, 0)
    for a, b in zip(default_set[:5], again, strict=True):
        _same(a, b)
    other = motion.synthesize(1, 1)[0]
    assert not np.allclose(other.head[:10, :2], default_set[0].head[:10, :2])
    lab = floors.lab()
    pts = jnp.asarray(np.concatenate([t.head[::20, :2] for t in default_set]), jnp.float32)
    clearance = np.asarray(jax.jit(jax.vmap(floors.signed_distance, (None, 0)))(lab, pts))
    assert clearance.min() >= 0.3  # users keep clear of furniture and walls


def test_split_holds_out_the_last_100_consecutive(default_set):
    train, test = motion.split(default_set)
    assert len(train) == 342 and len(test) == 100
    assert test[0].name == "traj_0342" and test[-1].name == "traj_0441"
    assert not {t.name for t in train} & {t.name for t in test}
    with pytest.raises(ValueError, match="cannot hold out"):
        motion.split(default_set[:5], 5)


def test_motion_bank_is_padded_and_indexable_in_jit():
    trajs = motion.synthesize(4, 2)
    bank = motion.MotionBank.from_trajectories(trajs)
    n = bank.length.tolist()
    assert bank.pose.shape == (4, max(n), 3) and bank.max_steps == max(n)
    i = int(np.argmin(n))
    assert np.all(np.asarray(bank.vel_world[i, n[i] :]) == 0)  # standing still after the end
    np.testing.assert_array_equal(
        np.asarray(bank.pose[i, n[i] :]), np.asarray(bank.pose[i, n[i] - 1 : n[i]]).repeat(max(n) - n[i], 0)
    )
    assert np.all(np.asarray(bank.request_step) < np.asarray(bank.length))
    # user-frame velocity is the world velocity rotated by -yaw
    yaw = np.asarray(bank.pose[..., 2])
    vw, vl = np.asarray(bank.vel_world), np.asarray(bank.vel_local)
    np.testing.assert_allclose(vl[..., 0], np.cos(yaw) * vw[..., 0] + np.sin(yaw) * vw[..., 1], atol=1e-5)
    # the HIP sits 2 m ahead and 0.3 m to the right, facing the user (steady heading: standing)
    r = int(bank.request_step[0])
    user, hip = np.asarray(bank.pose[0, r]), np.asarray(bank.hip[0, r])
    local = np.array([[np.cos(user[2]), np.sin(user[2])], [-np.sin(user[2]), np.cos(user[2])]]) @ (
        hip[:2] - user[:2]
    )
    np.testing.assert_allclose(local, [2.0, -0.3], atol=0.05)
    assert abs(np.angle(np.exp(1j * (hip[2] - user[2] - np.pi)))) < 0.05
    at = jax.jit(jax.vmap(bank.at))(jnp.arange(4), jnp.asarray(bank.request_step))
    assert at["requested"].all() and not at["ended"].any()
    np.testing.assert_allclose(at["pose"], bank.pose[jnp.arange(4), bank.request_step])
    with pytest.raises(ValueError, match="shorter than the longest"):
        motion.MotionBank.from_trajectories(trajs, max_steps=10)


def test_hip_is_configurable():
    (t,) = motion.synthesize(1, 4)
    f = motion.user_features(t, motion.HipConfig(distance=3.0, lateral=0.5, yaw_offset=0.0))
    r = int(f["request_step"])
    d = f["hip"][r, :2] - f["pose"][r, :2]
    assert np.linalg.norm(d) == pytest.approx(np.hypot(3.0, 0.5), abs=0.05)


def test_sample_dataset_ships_and_loads():
    trajs = motion.sample()
    assert len(trajs) == 4 and all(t.request_time > 5 for t in trajs)


def test_default_dataset_is_cached(tmp_path):
    first = motion.default_dataset(3, 11, cache=tmp_path, progress=False)
    (folder,) = (tmp_path / "motion").iterdir()
    assert sorted(p.name for p in folder.iterdir()) == [
        "traj_0000.mcap",
        "traj_0001.mcap",
        "traj_0002.mcap",
        "trajectories.npz",
    ]
    (folder / "traj_0000.mcap").unlink()  # the second call reads the npz, not the bags
    second = motion.default_dataset(3, 11, cache=tmp_path, progress=False)
    for a, b in zip(first, second, strict=True):
        _same(a, b)
    for a, b in zip(first[1:], motion.load(folder), strict=True):  # and the bags hold the same data
        _same(a, b)


def test_default_dataset_made_by_two_runs_at_once(tmp_path, monkeypatch):
    """Two runs started together both make the dataset; the one that finishes second finds the
    other's folder in place and keeps it (both once wrote into one shared .partial folder, and the
    second failed to rename it)."""
    from methd_jax.motion import dataset

    save, getpid = dataset.bags.save, dataset.os.getpid

    def save_while_another_run_finishes(folder, trajectories, **kw):
        save(folder, trajectories, **kw)
        monkeypatch.setattr(dataset.bags, "save", save)
        monkeypatch.setattr(dataset.os, "getpid", lambda: getpid() + 1)  # the other process
        motion.default_dataset(2, 5, cache=tmp_path, progress=False)
        monkeypatch.setattr(dataset.os, "getpid", getpid)

    monkeypatch.setattr(dataset.bags, "save", save_while_another_run_finishes)
    ours = motion.default_dataset(2, 5, cache=tmp_path, progress=False)
    (folder,) = (tmp_path / "motion").iterdir()  # no partial folder left behind
    assert (folder / "trajectories.npz").is_file()
    for a, b in zip(ours, motion.default_dataset(2, 5, cache=tmp_path, progress=False), strict=True):
        _same(a, b)


# --- recordings made by someone else --------------------------------------------------------------


def _write_foreign(
    path,
    *,
    head=None,
    wrist=None,
    request=None,
    rate=120.0,
    n=600,
    clock_offset_ns=0,
    wrist_offset_ns=0,
    gap=None,
):
    """A bag as a ROS 2 recorder would write it: 120 Hz, header stamps on the sensor clock, log
    times on the recorder's clock, one True on /haptic_request, wrist stamps 3 ms after the head's
    (plus ``wrist_offset_ns``); ``gap = (i, seconds)`` delays every message from the i-th on."""
    t = np.arange(n) / rate
    yaw = 0.3 * t
    default = np.concatenate(
        [np.stack([0.5 * t, np.zeros(n), np.full(n, 1.7)], 1), quat_from_yaw_pitch(yaw, 0 * t)], 1
    )
    head = default if head is None else head
    wrist = default - [0, 0.2, 0.8, 0, 0, 0, 0] if wrist is None else wrist
    start = 1_700_000_000 * 10**9
    with open(path, "wb") as f:
        w = Writer(f)
        ps = w.register_msgdef("geometry_msgs/msg/PoseStamped", bags.POSE_STAMPED_MSGDEF)
        bs = w.register_msgdef("std_msgs/msg/Bool", bags.BOOL_MSGDEF)
        for i in range(n):
            ns = start + round(t[i] * 1e9) + (round(gap[1] * 1e9) if gap and i >= gap[0] else 0)
            for topic, arr, lag in (("/head", head, 0), ("/wrist", wrist, 3_000_000 + wrist_offset_ns)):
                if arr is False:
                    continue
                p = arr[i]
                msg = {
                    "header": {
                        "stamp": {"sec": (ns + lag) // 10**9, "nanosec": (ns + lag) % 10**9},
                        "frame_id": "world",
                    },
                    "pose": {
                        "position": dict(zip("xyz", map(float, p[:3]), strict=True)),
                        "orientation": dict(zip("xyzw", map(float, p[3:]), strict=True)),
                    },
                }
                w.write_message(topic, ps, msg, log_time=ns + lag + clock_offset_ns + 2_000_000)
        if request is not False:
            k = int(0.8 * n) if request is None else request
            lag = clock_offset_ns + 2_000_000  # the recorder's clock and delay, as for the poses
            w.write_message("/haptic_request", bs, {"data": False}, log_time=start + lag)
            late = round(gap[1] * 1e9) if gap and k >= gap[0] else 0
            w.write_message(
                "/haptic_request", bs, {"data": True}, log_time=start + round(t[k] * 1e9) + lag + late
            )
        w.finish()
    return t, head


def test_a_foreign_ros2_recording_loads_and_is_resampled(tmp_path):
    t, _ = _write_foreign(tmp_path / "rec.mcap", clock_offset_ns=5 * 10**9)
    (traj,) = motion.load(tmp_path / "rec.mcap")
    assert traj.name == "rec"
    assert np.allclose(np.diff(traj.time), 0.01) and traj.time[-1] == pytest.approx(t[-1], abs=0.01)
    np.testing.assert_allclose(traj.head[:, 0], 0.5 * traj.time, atol=1e-9)  # resampled onto 100 Hz
    np.testing.assert_allclose(yaw_from_quat(traj.head[:, 3:]), 0.3 * traj.time, atol=1e-4)
    # the request's log time is moved onto the header-stamp clock (5 s offset and 2 ms lag removed)
    assert traj.request_time == pytest.approx(t[480], abs=1e-6)


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda p: p.write_text("not a bag"), "not an MCAP file"),
        (lambda p: p.write_bytes(b"\x89MCAP0\r\n" + bytes(100)), "truncated or corrupt MCAP|unreadable MCAP"),
        (lambda p: _write_foreign(p, head=False), "no messages on /head"),
        (lambda p: _write_foreign(p, request=False), "no messages on /haptic_request"),
    ],
)
def test_bad_files_fail_with_one_line_naming_the_file(tmp_path, setup, message):
    path = tmp_path / "bad.mcap"
    setup(path)
    with pytest.raises(MotionDataError, match=message) as err:
        motion.load(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_truncated_bag_is_rejected(tmp_path):
    good = tmp_path / "good.mcap"
    _write_foreign(good)
    data = good.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(MotionDataError, match=r"cut\.mcap: (truncated|unreadable)"):
        motion.load(cut)


def test_no_request_backwards_time_and_nan_are_rejected(tmp_path):
    n = 600
    p = tmp_path / "norequest.mcap"
    with open(p, "wb") as f:  # /haptic_request present but never True
        w = Writer(f)
        ps = w.register_msgdef("geometry_msgs/msg/PoseStamped", bags.POSE_STAMPED_MSGDEF)
        bs = w.register_msgdef("std_msgs/msg/Bool", bags.BOOL_MSGDEF)
        for i in range(n):
            msg = bags._pose_msg(10**9 + i * 10**7, np.array([0, 0, 1.7, 0, 0, 0, 1.0]))
            w.write_message("/head", ps, msg, log_time=10**9 + i * 10**7)
            w.write_message("/wrist", ps, msg, log_time=10**9 + i * 10**7)
            w.write_message("/haptic_request", bs, {"data": False}, log_time=10**9 + i * 10**7)
        w.finish()
    with pytest.raises(MotionDataError, match=r"norequest\.mcap: no haptic request"):
        motion.load(p)
    (tmp_path / "stamps").mkdir()
    t = np.arange(n) / 120.0
    head = np.concatenate([np.stack([0.5 * t, 0 * t, 0 * t + 1.7], 1), quat_from_yaw_pitch(0 * t, 0 * t)], 1)
    _write_foreign(tmp_path / "nan.mcap", head=np.where(np.arange(n)[:, None] == 300, np.nan, head))
    with pytest.raises(MotionDataError, match=r"nan\.mcap: /head pose 300 is not finite"):
        motion.load(tmp_path / "nan.mcap")
    # backwards: swap two stamps by writing the head messages out of order
    back = tmp_path / "back.mcap"
    with open(back, "wb") as f:
        w = Writer(f)
        ps = w.register_msgdef("geometry_msgs/msg/PoseStamped", bags.POSE_STAMPED_MSGDEF)
        bs = w.register_msgdef("std_msgs/msg/Bool", bags.BOOL_MSGDEF)
        order = list(range(n))
        order[200], order[201] = 201, 200
        for k, i in enumerate(order):
            msg = bags._pose_msg(10**9 + i * 10**7, np.array([0, 0, 1.7, 0, 0, 0, 1.0]))
            w.write_message("/head", ps, msg, log_time=10**9 + k * 10**7)
            w.write_message("/wrist", ps, msg, log_time=10**9 + k * 10**7)
            w.write_message("/haptic_request", bs, {"data": k > 500}, log_time=10**9 + k * 10**7)
        w.finish()
    with pytest.raises(MotionDataError, match=r"back\.mcap: /head timestamps go backwards .* at message 201"):
        motion.load(back)


def test_a_bad_file_in_a_directory_loads_nothing(tmp_path):
    motion.save(tmp_path, motion.synthesize(2, 0))
    (tmp_path / "traj_0001.mcap").write_text("garbage")
    with pytest.raises(MotionDataError, match=r"traj_0001\.mcap: not an MCAP file"):
        motion.load(tmp_path)
    with pytest.raises(MotionDataError, match="no such file"):
        motion.load(tmp_path / "missing")


def test_tracking_glitches_are_repaired_and_counted(tmp_path):
    n = 600
    t = np.arange(n) / 120.0
    head = np.concatenate([np.stack([0.5 * t, 0 * t, 0 * t + 1.7], 1), quat_from_yaw_pitch(0 * t, 0 * t)], 1)
    glitched = head.copy()
    glitched[[100, 101, 350], 0] += 0.5  # marker swaps: 0.5 m jumps within 8 ms
    _write_foreign(tmp_path / "glitch.mcap", head=glitched)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (traj,) = motion.load(tmp_path / "glitch.mcap")
    msgs = [str(w.message) for w in caught if issubclass(w.category, TrackingGlitchWarning)]
    assert (
        len(msgs) == 1
        and "repaired 3 tracking glitch sample(s) on /head" in msgs[0]
        and "glitch.mcap" in msgs[0]
    )
    np.testing.assert_allclose(traj.head[:, 0], 0.5 * traj.time, atol=1e-6)


def test_ros1_bags_convert_to_the_same_data(tmp_path):
    trajs = motion.synthesize(2, 9)
    for tr in trajs:
        bags.write_ros1_bag(tmp_path / "ros1" / f"{tr.name}.bag", tr)
    files = motion.convert(tmp_path / "ros1", tmp_path / "mcap")
    assert [f.name for f in files] == ["traj_0000.mcap", "traj_0001.mcap"]
    for a, b in zip(trajs, motion.load(tmp_path / "mcap"), strict=True):
        _same(a, b)
    (tmp_path / "junk.bag").write_text("nope")
    with pytest.raises(MotionDataError, match=r"junk\.bag: not a readable ROS 1 bag"):
        motion.convert(tmp_path / "junk.bag", tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing written for a bad input
    # random bytes named .bag: a one-line error naming the file
    (tmp_path / "random.bag").write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(MotionDataError, match=r"random\.bag: not a readable ROS 1 bag"):
        motion.convert(tmp_path / "random.bag", tmp_path / "out")
    # a destination that is a file, or holds the outputs already: refused, nothing overwritten
    (tmp_path / "a_file").write_text("mine")
    with pytest.raises(MotionDataError, match=r"a_file: exists and is not a directory"):
        motion.convert(tmp_path / "ros1", tmp_path / "a_file")
    before = (tmp_path / "mcap" / "traj_0000.mcap").read_bytes()
    with pytest.raises(MotionDataError, match=r"traj_0000\.mcap: already exists"):
        motion.convert(tmp_path / "ros1", tmp_path / "mcap")
    assert (tmp_path / "mcap" / "traj_0000.mcap").read_bytes() == before
    assert (tmp_path / "a_file").read_text() == "mine"


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "methd_jax.motion", *args], cwd=ROOT, capture_output=True, text=True
    )


def test_cli_synth_stats_and_plots(tmp_path):
    run = _cli("synth", "--n", "3", "--seed", "2", "--out", str(tmp_path / "set"))
    assert run.returncode == 0, run.stderr
    assert len(list((tmp_path / "set").glob("*.mcap"))) == 3
    run = _cli(
        "stats",
        str(ROOT / "assets" / "motion_sample"),
        "--plots",
        str(tmp_path / "png"),
        "--json",
        str(tmp_path / "s.json"),
    )
    assert run.returncode == 0, run.stderr
    assert "4 trajectories" in run.stdout and "thesis" in run.stdout
    for png in ("speed_boxplot.png", "trajectories.png"):
        assert (tmp_path / "png" / png).read_bytes()[:4] == b"\x89PNG"
    figures = json.loads((tmp_path / "s.json").read_text())
    assert figures["trajectories"] == 4 and 0 < figures["speed_mps"]["median"] < 1.9


def test_cli_errors_are_one_line(tmp_path):
    (tmp_path / "x.mcap").write_text("hello")
    for args in (
        ("stats", str(tmp_path / "x.mcap")),
        ("stats", str(tmp_path / "nothing")),
        ("convert", str(tmp_path / "x.mcap"), str(tmp_path / "o")),
    ):
        run = _cli(*args)
        assert run.returncode == 2, run.stderr
        lines = [line for line in run.stderr.splitlines() if line.startswith("error:")]
        assert len(lines) == 1 and "Traceback" not in run.stderr


def test_data_that_would_load_silently_wrong_is_refused_or_repaired(tmp_path):
    n = 600
    t = np.arange(n) / 120.0
    head = np.concatenate([np.stack([0.5 * t, 0 * t, 0 * t + 1.7], 1), quat_from_yaw_pitch(0 * t, 0 * t)], 1)
    zero_q = head.copy()
    zero_q[200, 3:] = 0.0
    _write_foreign(tmp_path / "zeroq.mcap", head=zero_q)
    with pytest.raises(MotionDataError, match=r"zeroq\.mcap: /head pose 200 has no valid orientation"):
        motion.load(tmp_path / "zeroq.mcap")
    _write_foreign(tmp_path / "wrist.mcap", wrist_offset_ns=1000 * 10**9)
    with pytest.raises(MotionDataError, match=r"wrist\.mcap: /wrist stamps cover 0 s of /head's"):
        motion.load(tmp_path / "wrist.mcap")
    for seconds in (1e4, 4e8):
        _write_foreign(tmp_path / "gap.mcap", gap=(300, seconds))
        with pytest.raises(MotionDataError, match=r"gap\.mcap: /head has a gap of .* s before message 300"):
            motion.load(tmp_path / "gap.mcap")
    # a glitch in the very first sample is repaired, not taken as the track
    first = head.copy()
    first[0, 0] += 1e9
    _write_foreign(tmp_path / "first.mcap", head=first)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        (traj,) = motion.load(tmp_path / "first.mcap")
    assert any("repaired 1 tracking glitch" in str(w.message) for w in caught)
    np.testing.assert_allclose(traj.head[1:, 0], 0.5 * traj.time[1:], atol=1e-6)


def test_the_motion_bag_reader_refuses_corrupt_files_cleanly(tmp_path):
    """Random bytes, cuts, bit flips and damaged spans (conftest.fuzz): a one-line error naming the
    file, or a trajectory of finite poses."""
    source = ROOT / "assets" / "motion_sample" / "traj_0003.mcap"
    path = tmp_path / "fuzzed.mcap"

    def target(data):
        path.write_bytes(data)
        try:
            traj = bags.read_bag(path)
        except MotionDataError as e:
            assert str(path) in str(e) and "\n" not in str(e)
            return "refused"
        assert isinstance(traj, Trajectory) and np.isfinite(traj.head).all() and np.isfinite(traj.wrist).all()
        return "accepted"

    counts = fuzz(target, source.read_bytes(), seed=0)
    assert counts["refused"] >= 10 and sum(counts.values()) >= 20, counts
