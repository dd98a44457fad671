"""``python -m train.run``: help, one-line errors on bad input, and a whole small run on disk."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import TINY_RUN

from methd_jax.jsonable import jsonable
from train import export
from train.presets import PRESETS, ConfigError, apply_overrides, preset
from train.run import CHUNK, main

TINY = [*TINY_RUN, "timesteps=8"]
SU_POLICY = Path(__file__).resolve().parents[1] / "assets" / "pretrained" / "su"


def test_help_lists_presets_and_options():
    done = subprocess.run(
        [sys.executable, "-m", "train.run", "--help"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    for name in ("quick", "su", "guide", "nav"):
        assert f"  {name} " in done.stdout
    for option in ("num_envs=2048", "ppo.learning_rate=0.0005", "env.lab=False", "guide_run=", "--resume"):
        assert option in done.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["su", "num_env=4"], "unknown option 'num_env'; did you mean 'num_envs'?"),
        (["su", "num_envs=four"], "num_envs expects an integer, got 'four'"),
        (["su", "num_envs=-8"], "num_envs must be at least 1, got -8"),
        (["su", "ppo.gamma=1.5"], "ppo.gamma must be in (0, 1]"),
        (["su", "env.lab=perhaps"], "env.lab expects true or false"),
        (["su", "env.floor=3"], "'env.floor' is a group"),
        (["su", "env.floor.room_size=13"], "env.floor.room_size expects 2 comma-separated values"),
        (["walk"], "unknown preset 'walk'"),
        (["su", "guide_run=runs/x"], "guide_run applies to env_name=nav only"),
        (["su", "checkpoint_keep=-1"], "checkpoint_keep must be >= 0 (0: every one), got -1"),
        (["su", "--bogus"], "unrecognized arguments: --bogus"),
    ],
)
def test_bad_input_exits_with_one_line(args, message, capsys, tmp_path):
    try:
        code = main([*args, "--out", str(tmp_path / "run")])
    except SystemExit as exit:  # argparse's own errors
        code = exit.code
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert message in err


def test_resume_of_a_missing_run_is_one_line(capsys, tmp_path):
    assert main(["--resume", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not a run folder" in err


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """One tiny finished run (two iterations, a checkpoint after each), shared read-only: tests that
    change it work on a copy."""
    run = tmp_path_factory.mktemp("small") / "run"
    assert main(["quick", *TINY, "checkpoint_every=1", "--out", str(run), "--quiet"]) == 0
    return run


def test_a_small_run_writes_everything_a_user_needs(small_run, capsys):
    run = small_run
    for name in ("config.json", "metrics.jsonl", "reward_curve.png", "README.md", "policy/params.npz"):
        assert (run / name).exists(), name
    assert list((run / "tb").glob("events.out.tfevents.*"))
    assert (run / "checkpoints" / "2").is_dir()
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2]
    assert {
        "loss/policy",
        "loss/value",
        "reward/distance",
        "reward/obstacle_collision",
        "learning_rate",
    } <= set(rows[0])
    meta = json.loads((run / "config.json").read_text())
    assert meta["preset"] == "quick" and meta["overrides"] == [*TINY, "checkpoint_every=1"]
    assert meta["config"]["num_envs"] == 8
    readme = (run / "README.md").read_text()
    assert "--resume" in readme and "export.load" in readme

    policy = export.load(run)
    assert policy.manifest["env"] == "su" and policy.manifest["observation_size"] == 72 + 25
    assert policy.manifest["observation_layout"]["lidar"] == [0, 72]
    action = np.asarray(policy(np.zeros((3, 97), np.float32)))
    assert action.shape == (3, 3) and np.all(np.abs(action) <= 1)
    # a second run into the same folder refuses rather than mixing checkpoints
    before = sorted(p.name for p in run.rglob("*"))
    assert main(["quick", *TINY, "--out", str(run), "--quiet"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert sorted(p.name for p in run.rglob("*")) == before


def test_a_checkpoint_exports_as_a_deployment_folder(small_run, tmp_path, capsys):
    from methd_jax import deploy

    final = export.load(small_run)  # the run's own export of its last checkpoint, iteration 2
    first = export.export_deployment(small_run, tmp_path / "d1", iteration=1, log=lambda *a: None)
    last = export.export_deployment(small_run, tmp_path / "d2", iteration=2, log=lambda *a: None)
    same = lambda a, b: all(  # noqa: E731
        np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )
    two, one = export.load(last), export.load(first)
    assert same(two.params, final.params) and np.array_equal(two.obs_mean, final.obs_mean)
    assert not same(one.params, final.params)  # one PPO update apart
    assert one.manifest["trained"]["iteration"] == 1 and two.manifest["trained"]["iteration"] == 2
    assert json.loads((first / "manifest.json").read_text())["run_config"]["preset"] == "quick"
    obs = np.random.default_rng(0).normal(size=(4, 97)).astype(np.float32)
    controller = deploy.Controller(first, backend="numpy")
    assert np.allclose(controller.policy(obs), np.asarray(one(obs)), atol=1e-5)
    # a missing iteration names the ones there; a policy folder has no checkpoints
    for argv, message in (
        ([str(small_run), "--iteration", "7"], "has no checkpoint at iteration 7 (it has: 1, 2;"),
        ([str(small_run / "policy"), "--iteration", "1"], "--iteration takes a run folder"),
    ):
        with pytest.raises(SystemExit) as e:
            export.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and err.strip().count("\n") == 0, err
    assert not list(small_run.glob(".checkpoint-*")) and not (small_run / "deploy-7").exists()


def test_several_checkpoints_export_as_their_weight_average(small_run, tmp_path, capsys):
    one = export.load(export.export_deployment(small_run, tmp_path / "d1", iteration=1, log=lambda *a: None))
    two = export.load(export.export_deployment(small_run, tmp_path / "d2", iteration=2, log=lambda *a: None))
    assert export.main([str(small_run), "--iteration", "2", "1"]) == 0
    folder = small_run / "deploy-avg-1-2"
    avg = export.load(folder)
    for a, b, m in zip(*(jax.tree.leaves(p.params) for p in (one, two, avg)), strict=True):
        np.testing.assert_allclose(m, (np.float64(a) + b) / 2, rtol=0, atol=1e-7)
    assert not all(map(np.array_equal, jax.tree.leaves(avg.params), jax.tree.leaves(two.params)))
    np.testing.assert_allclose(avg.obs_mean, (np.float64(one.obs_mean) + two.obs_mean) / 2, atol=1e-6)
    var = (np.float64(one.obs_std) ** 2 + np.float64(two.obs_std) ** 2) / 2
    np.testing.assert_allclose(avg.obs_std, np.sqrt(var), rtol=1e-5)
    assert avg.manifest["trained"]["averaged_iterations"] == [1, 2]
    assert avg.manifest["trained"]["iteration"] == 2
    shutil.rmtree(folder)
    for argv, message in (
        ([str(small_run), "--iteration", "1", "1"], "must be distinct"),
        ([str(small_run), "--iteration", "1", "5", "6"], "no checkpoint at iteration 5, 6 (it has: 1, 2;"),
    ):
        with pytest.raises(SystemExit) as e:
            export.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and err.strip().count("\n") == 0, err


def test_resume_falls_back_past_a_damaged_checkpoint(small_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(small_run, run)  # checkpoints 1 and 2
    for f in (run / "checkpoints" / "2").rglob("*"):
        if f.is_file():
            f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 3])  # a save cut short
    assert main(["--resume", str(run), "--quiet"]) == 0  # from checkpoint 1, to the end again
    rows = [json.loads(r) for r in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2]
    assert (run / "checkpoints" / "2.damaged").is_dir() and (run / "checkpoints" / "2").is_dir()
    assert export.load(run).manifest["trained"]["iteration"] == 2
    for f in (run / "checkpoints").rglob("*"):
        if f.is_file() and f.suffix != ".json":
            f.write_bytes(b"")
    assert main(["--resume", str(run), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "restores into this run's configuration" in err and len(err.strip().splitlines()) == 1


def test_resume_with_more_timesteps_carries_a_finished_run_on(small_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(small_run, run)  # finished: iterations 1 and 2 of timesteps=8
    before = (run / "metrics.jsonl").read_text()
    for argv, message in (
        (["timesteps=4"], "can extend a run, not shorten it: timesteps=4 is below the run's timesteps=8"),
        (["num_envs=4"], "timesteps=N alone may extend it"),
        (["timesteps=16", "seed=1"], "timesteps=N alone may extend it"),
        (["su_cpu"], "--resume continues the run's own preset; leave out 'su_cpu'"),
    ):
        assert main(["--resume", str(run), *argv, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert (run / "metrics.jsonl").read_text() == before  # refused before anything is written
    assert main(["--resume", str(run), "timesteps=16", "--quiet"]) == 0
    rows = [json.loads(r) for r in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4]
    assert (run / "metrics.jsonl").read_text().startswith(before)  # the first two rows as they were
    meta = json.loads((run / "config.json").read_text())
    assert meta["config"]["timesteps"] == 16 and meta["overrides"][-1] == "timesteps=16"
    assert export.load(run).manifest["trained"]["iteration"] == 4
    assert main(["--resume", str(run), "--quiet"]) == 0  # the stored length is now 16: nothing to do
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 4


def test_init_from_starts_from_the_other_runs_learned_state(small_run, tmp_path, capsys):
    import jax
    from flax import traverse_util

    from train import run as run_lib

    source = small_run
    # another reward, and an environment state of another layout (one more metric): only the
    # learned parts come over
    overrides = [*TINY, "env.weights.velocity=-0.6", "env.request_weight=1", f"init_from={source}"]
    config = apply_overrides(preset("quick"), overrides)
    setup = run_lib.build(config)
    fresh = jax.jit(setup.trainer.init)(jax.random.key(7))
    warm = run_lib._warm_start(fresh, source, setup)
    exported = export.load(source)  # the source's final parameters and observation statistics
    ours = traverse_util.flatten_dict(jax.device_get(warm.params), sep="/")
    theirs = traverse_util.flatten_dict(jax.device_get(exported.params), sep="/")
    assert set(theirs) <= set(ours)
    for k, v in theirs.items():
        np.testing.assert_array_equal(np.asarray(ours[k]), np.asarray(v), err_msg=k)
    assert any(
        not np.array_equal(np.asarray(ours[k]), np.asarray(v))
        for k, v in traverse_util.flatten_dict(jax.device_get(fresh.params), sep="/").items()
    )
    assert int(warm.iteration) == 0  # a new run, not a resume
    # a run whose network does not fit is refused in one line
    assert main(["quick", *TINY, "hidden=16", f"init_from={source}", "--out", str(tmp_path / "b")]) == 2
    assert "does not fit this run" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # nothing left behind that would block the corrected command
    # from the exported policy folder the observation statistics keep the weight of the
    # transitions they were estimated on, as a resumed run's do: one iteration's weight let the
    # first iterations re-estimate them and shift the inputs under the loaded policy
    from_policy = run_lib._warm_start(fresh, source / "policy", setup)
    assert float(from_policy.obs_stats.count) == exported.manifest["trained"]["transitions"]
    assert exported.manifest["trained"]["transitions"] > setup.trainer.transitions_per_iteration
    stats = jax.device_get(from_policy.obs_stats)
    np.testing.assert_allclose(stats.mean, np.asarray(exported.obs_mean), rtol=1e-6)
    np.testing.assert_allclose(stats.var, np.asarray(exported.obs_std) ** 2, rtol=1e-5)
    # a field the policy never saw (the footprint's clearance per sector) starts at zero weight and
    # unscaled, and does not cost the other fields' statistics their weight
    sectors = apply_overrides(config, ["env.clearance_sectors=18"])
    setup = run_lib.build(sectors)
    warm = run_lib._warm_start(jax.jit(setup.trainer.init)(jax.random.key(7)), source / "policy", setup)
    field = setup.env.observation_layout["clearance"]
    assert float(warm.obs_stats.count) == exported.manifest["trained"]["transitions"]
    stats = jax.device_get(warm.obs_stats)
    assert (
        np.asarray(stats.mean)[field].tolist() == [0.0] * 18
        and np.asarray(stats.var)[field].tolist() == [1.0] * 18
    )
    np.testing.assert_allclose(
        np.asarray(stats.mean)[: field.start], np.asarray(exported.obs_mean), rtol=1e-6
    )
    obs = np.asarray(warm.env_state.obs)
    policy = export.Policy(exported.manifest, warm.params, stats.mean, stats.std)
    without = export.Policy(
        exported.manifest, exported.params, stats.mean[: field.start], stats.std[: field.start]
    )
    for clearance in (0.0, 1.5):
        seen = jax.numpy.asarray(obs).at[:, field].set(clearance)
        np.testing.assert_allclose(policy(seen), without(seen[:, : field.start]), atol=1e-6)
    # the same source's exported policy starts a two-user (NavRL) run
    _check_two_user_start_from_su_policy(source)


def _check_two_user_start_from_su_policy(source):
    """A NavRL run warm-started from an exported SU policy acts, on any second user, exactly as the
    SU policy does without one; its normaliser takes user 0's statistics for user 1."""
    import jax
    import jax.numpy as jnp

    from train import run as run_lib

    su = export.load(source)
    nav = apply_overrides(
        preset("nav"), [*TINY, "env.floor.num_circles=0,0", f"init_from={source / 'policy'}"]
    )
    setup = run_lib.build(nav)
    warm = run_lib._warm_start(jax.jit(setup.trainer.init)(jax.random.key(3)), source / "policy", setup)
    layout = setup.env.observation_layout
    u0, u1 = layout["user0"], layout["user1"]
    mean, std = np.asarray(warm.obs_stats.mean), np.asarray(warm.obs_stats.std)
    theirs = slice(*su.manifest["observation_layout"]["user0"])
    np.testing.assert_allclose(mean[u0], np.asarray(su.obs_mean)[theirs], rtol=1e-6)
    np.testing.assert_allclose(mean[u1], mean[u0], rtol=1e-6)
    np.testing.assert_allclose(std[u1], std[u0], rtol=1e-5)
    # user 1's borrowed statistics weigh one iteration of data, so that they adapt to user 1
    assert float(warm.obs_stats.count) == setup.trainer.transitions_per_iteration

    obs_nav = jax.random.normal(jax.random.key(0), (16, setup.env.observation_size)) * 2
    obs_su = jnp.concatenate([obs_nav[:, : u1.start], obs_nav[:, u1.stop :]], axis=1)
    warm_policy = export.Policy(su.manifest, warm.params, warm.obs_stats.mean, warm.obs_stats.std)
    np.testing.assert_allclose(warm_policy(obs_nav), su(obs_su), atol=1e-5)
    other = obs_nav.at[:, u1].set(100.0)
    np.testing.assert_allclose(warm_policy(other), su(obs_su), atol=1e-5)

    # a policy of another network, or a folder that holds none, is refused in one line
    wide_setup = run_lib.build(apply_overrides(preset("nav"), [*TINY, "hidden=16,16"]))
    with pytest.raises(ConfigError, match="is not this run's"):
        run_lib._warm_start(warm, source / "policy", wide_setup)
    with pytest.raises(ConfigError, match="neither a run folder with checkpoints nor a policy folder"):
        run_lib._warm_start(warm, source / "tb", setup)


def test_critic_warmup_needs_a_start():
    with pytest.raises(ConfigError, match="critic_warmup must be >= 0 and needs init_from"):
        apply_overrides(preset("guide"), ["critic_warmup=3"])
    with pytest.raises(ConfigError, match="critic_warmup must be >= 0"):
        apply_overrides(preset("nav_cpu"), ["critic_warmup=-1"])
    assert apply_overrides(preset("nav_cpu"), ["critic_warmup=3"]).critic_warmup == 3


def test_presets_are_the_thesis_table():
    su, guide, nav = (PRESETS[n][1] for n in ("su", "guide", "nav"))
    for c in (su, guide, nav):
        assert (c.ppo.rollouts, c.ppo.epochs, c.ppo.minibatches) == (48, 5, 8)
        assert (c.ppo.gamma, c.ppo.lam, c.ppo.learning_rate, c.ppo.entropy_scale) == (0.99, 0.95, 5e-4, 0.005)
    assert (su.num_envs, nav.num_envs, guide.num_envs) == (2048, 2048, 4096)
    assert (su.timesteps, nav.timesteps, guide.timesteps) == (960_000, 960_000, 240_000)
    assert nav.env.num_users == 2 and su.env.num_users == 1


def _random_guide_run(folder):
    """A run folder holding a GuideRL policy (random init: its training is tested in test_ppo)."""
    from conftest import export_random_policy

    import envs
    import networks

    env = envs.make("guide", motion="sample")
    return export_random_policy(folder, env, "guide", networks.GuideActorCritic(hidden=(16, 16)), seed=2)


def test_guide_run_is_the_nav_runs_goal_source(tmp_path, monkeypatch):
    """What ``guide_run=`` does without training (the slow test below trains with it): the NavRL
    environment steers its goal with that GuideRL policy; a policy of another kind is refused."""
    from train import run as run_lib

    policy = export.load(_random_guide_run(tmp_path / "guide"))
    setup = run_lib.build(apply_overrides(preset("nav"), [*TINY, f"guide_run={tmp_path / 'guide'}"]))
    obs = np.random.default_rng(0).normal(size=(4, 15)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(setup.env.guide_policy(obs)), np.asarray(policy(obs)))
    assert run_lib.build(apply_overrides(preset("nav"), TINY)).env.guide_policy is None  # scripted
    # a folder named relative to where the run starts is kept absolute: config.json and the
    # manifests of the run's policies (which name the GuideRL policy) are read from anywhere
    monkeypatch.chdir(tmp_path)
    relative = run_lib.build(apply_overrides(preset("nav"), [*TINY, "guide_run=guide", "init_from=x/policy"]))
    assert relative.config.guide_run == str(tmp_path / "guide")
    assert relative.config.init_from == str(tmp_path / "x" / "policy")
    assert run_lib.dependencies(relative.config) == {"guide": str(tmp_path / "guide")}
    with pytest.raises(ConfigError, match="holds a 'su' policy, not a guide policy"):
        run_lib.build(apply_overrides(preset("nav"), [*TINY, f"guide_run={SU_POLICY}"]))


def test_guide_with_wrists_starts_from_a_policy_without_them(tmp_path):
    """``env.wrist=true init_from=<a 15-input GuideRL policy>``: the started policy acts as the
    source whatever the wrists read; ``noise_restart`` puts the action noise back at
    ``init_log_std``; a NavRL environment feeds such a policy the users' wrists."""
    import jax
    import jax.numpy as jnp

    from envs.nav import guide_takes_wrist
    from train import run as run_lib

    source = _random_guide_run(tmp_path / "guide")
    old = export.load(source)
    args = ["env.motion=sample", "hidden=16,16", "num_envs=4", f"init_from={source}"]
    setup = run_lib.build(apply_overrides(preset("guide"), [*args, "env.wrist=true"]))
    fresh = jax.jit(setup.trainer.init)(jax.random.key(1))
    warm = run_lib._warm_start(fresh, source, setup)
    obs = jax.random.normal(jax.random.key(0), (32, 17))
    new = export.Policy(
        {**old.manifest, "observation_layout": {"guide": [0, 15], "wrist": [15, 17]}},
        warm.params,
        warm.obs_stats.mean,
        warm.obs_stats.std,
    )
    assert guide_takes_wrist(new) and not guide_takes_wrist(old)
    np.testing.assert_allclose(new(obs), old(obs[:, :15]), atol=1e-6)
    np.testing.assert_allclose(new(obs.at[:, 15:].set(-0.3)), old(obs[:, :15]), atol=1e-6)
    old_log_std = np.asarray(old.params["params"]["actor"]["log_std"])
    np.testing.assert_array_equal(np.asarray(warm.params["params"]["actor"]["log_std"]), old_log_std)
    restarted = apply_overrides(
        preset("guide"), [*args, "env.wrist=true", "noise_restart=true", "init_log_std=-0.5"]
    )
    setup = run_lib.build(restarted)
    warm = run_lib._warm_start(jax.jit(setup.trainer.init)(jax.random.key(1)), source, setup)
    assert np.asarray(warm.params["params"]["actor"]["log_std"]).tolist() == [-0.5]
    with pytest.raises(ConfigError, match="noise_restart needs init_from"):
        apply_overrides(preset("guide"), ["noise_restart=true"])

    # the NavRL environment hands a wrist policy the users' wrist heights
    from envs.nav import NavEnv

    seen = []

    def wrist_policy(obs):
        seen.append(obs.shape)
        return jnp.zeros(1)

    wrist_policy.manifest = new.manifest
    env = NavEnv(run_lib.build(apply_overrides(preset("nav"), TINY)).env.config, guide_policy=wrist_policy)
    state = env.reset(jax.random.key(0))
    env.step(state, jnp.zeros(3))
    assert seen and all(shape == (17,) for shape in seen)


@pytest.mark.slow
def test_nav_trains_with_a_guide_run_as_its_goal_source(tmp_path, capsys, monkeypatch):
    guide = tmp_path / "guide"
    _random_guide_run(guide)
    nav = tmp_path / "nav"
    monkeypatch.chdir(tmp_path)  # the GuideRL folder named relative to here
    args = ["nav", *TINY, "guide_run=guide", "--out", str(nav), "--quiet"]
    assert main(args) == 0
    manifest = export.load(nav).manifest
    assert manifest["env"] == "nav" and manifest["observation_size"] == 72 + 33
    # which the exported policy's manifest records so that it is found from elsewhere
    monkeypatch.chdir(tmp_path.parent)
    assert export.dependencies(nav) == {"guide": str(guide)}
    # a policy of the wrong kind is refused with one line
    assert main(["nav", *TINY, f"guide_run={nav}", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not a guide policy" in err


def test_max_minutes_ends_early_with_a_checkpoint_and_the_export(tmp_path, capsys):
    run = tmp_path / "run"
    args = ["quick", *TINY, "timesteps=400", "--out", str(run), "--quiet"]
    assert main([*args, "--max-minutes", "1e-6"]) == 0  # out of time after the first call
    rows = (run / "metrics.jsonl").read_text().splitlines()
    assert len(rows) == CHUNK and (run / "checkpoints" / str(CHUNK)).is_dir()
    assert export.load(run).manifest["trained"]["iteration"] == CHUNK
    # the throughput counts the iterations done, not those the run would have done
    per = json.loads(rows[0])["transitions"]
    chunk_s = sum(json.loads(r)["seconds"] for r in rows)
    readme = (run / "README.md").read_text()
    reported = float(re.search(r"\| throughput \| ([\d,]+) transitions/s", readme)[1].replace(",", ""))
    assert 0 < reported <= CHUNK * per / chunk_s
    metrics = run / "metrics.jsonl"
    metrics.write_text(metrics.read_text() + f'{{"iteration": {CHUNK + 1}, "loss/pol')  # killed mid-append
    assert main(["--resume", str(run), "--quiet", "--max-minutes", "1e-6"]) == 0  # continues by a call
    iterations = [json.loads(r)["iteration"] for r in metrics.read_text().splitlines()]
    assert iterations == list(range(1, 2 * CHUNK + 1))
    # a metrics file that is not this run's is refused before anything is written
    config = (run / "config.json").read_text()
    metrics.write_text('{"epoch": 3}\n{"epoch": 4}\n')
    assert main(["--resume", str(run), "--quiet", "--max-minutes", "1e-6"]) == 2
    err = capsys.readouterr().err
    assert "metrics.jsonl: line 1 is not a metrics row" in err and len(err.strip().splitlines()) == 1
    assert (run / "config.json").read_text() == config and metrics.read_text().startswith('{"epoch": 3}')
    assert main([*args[:-3], "--out", str(tmp_path / "b"), "--max-minutes", "0"]) == 2
    assert "--max-minutes must be positive" in capsys.readouterr().err


def test_out_never_overwrites_what_a_user_has(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "README.md").write_text("my notes")
    assert main(["quick", *TINY, "--out", str(mine), "--quiet"]) == 2
    assert "is not an empty folder" in capsys.readouterr().err
    assert (mine / "README.md").read_text() == "my notes" and sorted(mine.iterdir()) == [mine / "README.md"]
    afile = tmp_path / "file"
    afile.write_text("x")
    assert main(["quick", *TINY, "--out", str(afile), "--quiet"]) == 2
    assert afile.read_text() == "x"


def test_bad_motion_data_is_one_line_in_train_and_evaluate(tmp_path, capsys):
    from train import evaluate

    bags = tmp_path / "bags"
    bags.mkdir()
    (bags / "a.mcap").write_text("not a bag")
    assert main(["quick", *TINY, f"env.motion={bags}", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert (
        evaluate.main(["--motion", str(bags), "--no-pretrained", "--out", str(tmp_path / "e"), "--quiet"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("a.mcap: not an MCAP file" in line for line in err), err


def test_a_run_resumes_with_the_configuration_it_stored(tmp_path):
    """--resume reads the resolved configuration of config.json: a run started from Python (no
    preset) loads, and a preset changed since does not change an existing run."""
    import dataclasses

    from train import run as run_lib

    mine = dataclasses.replace(preset("guide"), num_envs=24, hidden=(7, 5), seed=11)
    folder = tmp_path / "custom"
    folder.mkdir()
    meta = {"preset": "custom", "overrides": [], "config": jsonable(mine)}
    (folder / "config.json").write_text(json.dumps(meta))
    assert run_lib.load_config(folder) == ("custom", [], mine)

    quick = apply_overrides(preset("quick"), ["seed=3"])
    then = dataclasses.replace(quick, num_envs=64)  # what "quick" named when that run started
    meta = {"preset": "quick", "overrides": ["seed=3"], "config": jsonable(then)}
    (folder / "config.json").write_text(json.dumps(meta))
    assert run_lib.load_config(folder)[2] == then != quick

    (folder / "config.json").write_text(json.dumps({**meta, "config": {"env_name": "walk"}}))
    with pytest.raises(ConfigError, match="its configuration does not load"):
        run_lib.load_config(folder)
