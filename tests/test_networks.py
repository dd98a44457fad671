import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import networks
from networks import ActorCritic, GuidePolicy, actor_critic, count, policy_count


@pytest.mark.parametrize(("state_size", "thesis"), [(25, 702_674), (33, 706_770)], ids=["su", "nav"])
def test_actor_critic_matches_the_thesis_parameter_count(state_size, thesis):
    net = ActorCritic()
    obs = jnp.zeros((4, 720 + state_size))
    params = net.init(jax.random.key(0), obs)
    n = policy_count(params)
    assert abs(n - thesis) / thesis < 0.02 and n == thesis + 20  # channels (64, 32, 32, 32)
    assert count(params) == n + 513  # plus the value head
    mean, log_std, value = jax.jit(net.apply)(params, obs)
    assert mean.shape == (4, 3) and log_std.shape == (4, 3) and value.shape == (4,)
    # the encoder reduces 720 rays to 55 positions before the flatten, as the kernels/strides imply
    conv3 = params["params"]["encoder"]["conv3"]["kernel"]
    assert conv3.shape == (3, 32, 32)
    assert params["params"]["encoder"]["project"]["kernel"].shape == (55 * 32, 64)


def test_guide_policy_has_exactly_18690_parameters():
    params = GuidePolicy().init(jax.random.key(0), jnp.zeros(15))
    assert count(params) == 18_690
    mean, log_std = GuidePolicy().apply(params, jnp.ones((7, 15)))
    assert mean.shape == (7, 1) and np.all(np.asarray(log_std) == 0.0)


def test_actor_critic_uses_the_lidar_and_the_state():
    net = ActorCritic()
    obs = jax.random.uniform(jax.random.key(1), (2, 745), maxval=3.0)
    params = net.init(jax.random.key(0), obs)
    base = net.apply(params, obs)[0]
    lidar_changed = net.apply(params, obs.at[:, 100].add(1.0))[0]
    state_changed = net.apply(params, obs.at[:, 740].add(1.0))[0]
    assert not np.allclose(base, lidar_changed) and not np.allclose(base, state_changed)


@pytest.mark.parametrize(
    ("length", "kernel", "stride"),
    # the encoder's layers at 90 and 720 rays, a kernel shorter than its stride, unused tail samples
    [(40, 4, 1), (40, 4, 3), (40, 4, 4), (90, 8, 4), (21, 5, 3), (720, 8, 4), (179, 5, 3), (23, 2, 5)],
)
def test_conv1d_and_its_gradient_match_xla_convolution(length, kernel, stride):
    rng = np.random.default_rng(stride)
    x = jnp.asarray(rng.normal(size=(5, length, 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(kernel, 3, 6)), jnp.float32)
    g = jnp.asarray(rng.normal(size=(5, (length - kernel) // stride + 1, 6)), jnp.float32)

    def xla(x, w):
        return jax.lax.conv_general_dilated(x, w, (stride,), "VALID", dimension_numbers=("NWC", "WIO", "NWC"))

    ours = actor_critic.conv1d(x, w, stride)
    np.testing.assert_allclose(ours, xla(x, w), rtol=1e-5, atol=1e-5)
    want = jax.vjp(xla, x, w)[1](g)
    got = jax.vjp(lambda x, w: actor_critic.conv1d(x, w, stride), x, w)[1](g)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_guide_actor_critic_keeps_the_policy_at_18690_and_adds_a_critic():
    net = networks.GuideActorCritic()
    params = net.init(jax.random.key(0), jnp.zeros((2, 15)))
    mean, log_std, value = net.apply(params, jnp.ones((2, 15)))
    assert mean.shape == log_std.shape == (2, 1) and value.shape == (2,)
    assert networks.policy_count(params) == 18_690
    assert networks.count(params) == 2 * 18_690 - 1  # the critic: the same MLP without a log-std


def test_too_few_rays_for_the_encoder_is_a_clear_error():
    with pytest.raises(ValueError, match="too few"):
        networks.ActorCritic(num_rays=40).init(jax.random.key(0), jnp.zeros((1, 40 + 25)))


def test_from_spec_rebuilds_the_module():
    net = networks.from_spec({"class": "ActorCritic", "hidden": [16], "num_rays": 72, "init_log_std": -1.0})
    params = net.init(jax.random.key(0), jnp.zeros((1, 97)))
    assert np.allclose(params["params"]["log_std"], -1.0)
    assert params["params"]["body0"]["kernel"].shape == (64 + 25, 16)
    with pytest.raises(ValueError, match="unknown network class"):
        networks.from_spec({"class": "Transformer"})


@pytest.mark.parametrize(
    "net, size", [(networks.GuideActorCritic(), 15), (networks.ActorCritic(num_rays=90), 115)]
)
def test_outputs_are_named(net, size):
    obs = jax.random.normal(jax.random.key(1), (3, size))
    out = net.apply(net.init(jax.random.key(0), obs), obs)
    assert isinstance(out, networks.Outputs)
    assert out.mean.shape == out.log_std.shape == (3, 1 if size == 15 else 3) and out.value.shape == (3,)
    assert out.mean is out[0] and out.value is out[2]


def test_the_normaliser_is_the_same_line_in_numpy_and_jax():
    from methd_jax.normalise import normalise

    rng = np.random.default_rng(0)
    x, mean, std = rng.normal(size=(4, 6)) * 9, rng.normal(size=6), rng.uniform(0.5, 2, size=6)
    want = np.clip((x - mean) / std, -5.0, 5.0)
    got_np = normalise(x, mean, std, 5.0)
    got_jax = jax.jit(lambda a: normalise(a, jnp.asarray(mean), jnp.asarray(std), 5.0))(jnp.asarray(x))
    assert isinstance(got_np, np.ndarray) and np.abs(got_np).max() == 5.0
    np.testing.assert_allclose(got_np, want)
    np.testing.assert_allclose(got_jax, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(normalise(x, mean, std, 0.0), (x - mean) / std)  # clip 0: unclipped


def test_the_inference_factory_is_what_ppo_and_export_act_with(tmp_path):
    """networks.make_inference_fn: the deterministic action is clip(mean, -1, 1) of the normalised,
    clipped observation; a sample scatters around the mean with exp(log_std); PPO's policy and an
    exported policy give the same actions."""
    from conftest import export_random_policy

    from train import export
    from train.ppo import PPOConfig, RunningStats, Trainer

    net = networks.GuideActorCritic(hidden=(16, 16), init_log_std=-1.0)
    params = net.init(jax.random.key(0), jnp.zeros(15))
    rng = np.random.default_rng(0)
    obs = jnp.asarray(rng.normal(size=(256, 15)) * 10, jnp.float32)
    mean, std = (
        jnp.asarray(rng.normal(size=15), jnp.float32),
        jnp.asarray(rng.uniform(0.5, 2, 15), jnp.float32),
    )
    make_policy = networks.make_inference_fn(net, 5.0)
    want = np.clip(np.asarray(net.apply(params, jnp.clip((obs - mean) / std, -5, 5)).mean), -1, 1)
    np.testing.assert_allclose(make_policy(params, mean, std)(obs), want, atol=1e-6)
    samples = make_policy(params, mean, std, deterministic=False)(obs, jax.random.key(1))
    raw = np.asarray(net.apply(params, jnp.clip((obs - mean) / std, -5, 5)).mean)
    assert 0.3 < float(np.std(np.asarray(samples) - raw)) < 0.45  # exp(-1) = 0.37

    class Env:  # Trainer needs only the sizes to build its policy
        observation_size, action_size = 15, 1

    trainer = Trainer(Env(), net, PPOConfig(obs_clip=5.0, rollouts=2, minibatches=1), num_envs=2)
    stats = RunningStats(mean, std**2 - 1e-8, jnp.float32(10.0))
    np.testing.assert_allclose(trainer.policy(params, stats, obs), want, atol=1e-5)

    from envs.guide import GuideConfig

    env = types.SimpleNamespace(
        observation_size=15, action_size=1, observation_layout={"guide": slice(0, 15)}, config=GuideConfig()
    )
    policy = export.load(export_random_policy(tmp_path, env, "guide", net, seed=3))
    z = np.clip((np.asarray(obs) - np.asarray(policy.obs_mean)) / np.asarray(policy.obs_std), -5, 5)
    expected = np.clip(np.asarray(policy.network.apply(policy.params, jnp.asarray(z)).mean), -1, 1)
    np.testing.assert_allclose(policy(obs), expected, atol=1e-5)
