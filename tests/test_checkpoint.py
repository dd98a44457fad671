"""``train.checkpoint``: leaves saved under their path in the state; older checkpoints (leaves by
flat index) still restore."""

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from train import checkpoint as ckpt


def _state():
    return {
        "params": {"body_0": {"kernel": jnp.arange(6.0).reshape(2, 3), "bias": jnp.ones(3)}},
        "key": jax.random.key(7),
        "empty": jnp.zeros((0, 2)),  # orbax saves no empty arrays: kept from the template
        "iteration": jnp.int32(12),
        "history": [jnp.full(2, 3.0), jnp.float32(-1.0)],
    }


def _same(a, b) -> bool:
    unwrap = lambda x: jax.random.key_data(x) if ckpt._is_key(x) else x  # noqa: E731
    return all(
        np.array_equal(unwrap(x), unwrap(y))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


def test_leaves_are_saved_under_their_path_and_restore(tmp_path):
    state = _state()
    store = ckpt.Checkpoints(tmp_path)
    store.save(3, state)
    saved = store._manager.item_metadata(3)
    assert set(saved) == {"params", "key", "iteration", "history"}
    assert set(saved["params"]["body_0"]) == {"kernel", "bias"}
    like = jax.tree.map(jnp.zeros_like, state) | {"key": jax.random.key(0)}
    restored = store.restore(like)
    assert _same(restored, state) and jax.dtypes.issubdtype(restored["key"].dtype, jax.dtypes.prng_key)


def test_a_checkpoint_with_leaves_by_index_still_restores(tmp_path):
    state = _state()
    store = ckpt.Checkpoints(tmp_path)
    legacy = {f"{i:05d}": ckpt._saved(x) for i, x in enumerate(jax.tree.leaves(state)) if x.size}
    store._manager.save(5, args=ocp.args.StandardSave(legacy), force=True)
    store._manager.wait_until_finished()
    assert _same(store.restore(jax.tree.map(jnp.zeros_like, state) | {"key": jax.random.key(0)}), state)


def test_a_state_of_another_structure_does_not_restore(tmp_path):
    store = ckpt.Checkpoints(tmp_path)
    store.save(1, _state())
    other = _state()
    other["params"]["body_1"] = {"kernel": jnp.zeros((3, 3))}
    with pytest.raises(Exception):  # noqa: B017  (orbax raises its own kinds; restore_intact names them)
        store.restore(other)
    with pytest.raises(ckpt.CheckpointError, match="restores into this run"):
        store.restore_intact(other)


def test_named_fields_restore_whatever_the_rest_of_the_state_holds(tmp_path):
    from flax import struct

    @struct.dataclass
    class State:
        params: dict
        stats: jax.Array
        env: dict

    saved = State(params=_state()["params"], stats=jnp.arange(4.0), env={"reward/a": jnp.ones(5)})
    store = ckpt.Checkpoints(tmp_path)
    store.save(2, saved)
    zeros = jax.tree.map(jnp.zeros_like, saved)
    # the environments report one more metric now: a whole restore refuses, the learned fields come
    like = zeros.replace(env={"reward/a": jnp.zeros(5), "reward/b": jnp.zeros(5)})
    with pytest.raises(Exception):  # noqa: B017
        store.restore(like)
    got = store.restore_fields(like, ("params", "stats"))
    assert set(got) == {"params", "stats"}
    assert _same(got["params"], saved.params) and _same(got["stats"], saved.stats)
    # a field of another shape is named
    with pytest.raises(ValueError, match=r"stats is \(4,\) there and \(3,\) here"):
        store.restore_fields(like.replace(stats=jnp.zeros(3)), ("stats",))
    with pytest.raises(KeyError, match="has no 'missing'"):
        store.restore_fields(like, ("missing",))


@pytest.mark.parametrize(("keep", "kept"), [(3, [3, 4, 5]), (None, [1, 2, 3, 4, 5])])
def test_the_newest_keep_are_kept_or_every_one(tmp_path, keep, kept):
    store = ckpt.Checkpoints(tmp_path, keep=keep)
    for step in range(1, 6):
        store.save(step, _state())
    assert store.steps() == kept and store.latest() == 5
    store.close()
