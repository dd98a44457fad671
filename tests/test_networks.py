import jax
import jax.numpy as jnp
import numpy as np
import pytest

from networks import ActorCritic, GuidePolicy, count, policy_count


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
