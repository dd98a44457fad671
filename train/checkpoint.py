"""Orbax checkpoints of a whole :class:`train.ppo.TrainState`.

The environments' state is saved with the parameters, optimiser state, normaliser statistics,
iteration and key, so a resumed run continues exactly where it stopped (bit-identical on CPU).
Orbax saves neither typed PRNG keys nor empty arrays (MJX keeps a few, such as ``act`` of a model
without actuator states), so the state is saved as a nested dict of its non-empty leaves keyed by
their path in the state (``params/params/body_0/kernel``, ``env_state/pipeline_state/robot/qpos``),
keys as their raw data, and rebuilt from a state of the same structure on restore. Checkpoints
written before 2026-11-28 keyed the leaves by their index in the flattened state; they still
restore.
"""

from __future__ import annotations

from pathlib import Path

import jax
import orbax.checkpoint as ocp


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _saved(x):
    return jax.random.key_data(x) if _is_key(x) else x


def _name(entry) -> str:
    for attr in ("name", "key", "idx"):  # GetAttrKey, DictKey, SequenceKey / FlattenedIndexKey
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    raise TypeError(f"unexpected pytree path entry {entry!r}")


def _by_path(tree) -> dict:
    """The non-empty leaves of ``tree`` in nested dicts, one level per step of their path."""
    out: dict = {}
    for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]:
        if not x.size:
            continue
        names = [_name(e) for e in path]
        node = out
        for n in names[:-1]:
            node = node.setdefault(n, {})
        node[names[-1]] = _saved(x)
    return out


def _by_index(tree) -> dict:
    """The layout of checkpoints written before 2026-11-28: leaves keyed by their flat index."""
    leaves = jax.tree.leaves(tree)
    return {f"{i:05d}": _saved(x) for i, x in enumerate(leaves) if x.size}


def _rebuilt(like, lookup):
    """``like`` with each non-empty leaf replaced by ``lookup(path, index)`` (keys re-wrapped)."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = []
    for i, (path, x) in enumerate(flat):
        if x.size:
            r = lookup([_name(e) for e in path], i)
            x = jax.random.wrap_key_data(r, impl=jax.random.key_impl(x)) if _is_key(x) else r
        leaves.append(x)
    return jax.tree.unflatten(treedef, leaves)


class CheckpointError(ValueError):
    """No checkpoint of a run folder can be restored (the message says which were tried)."""


class Checkpoints:
    """Numbered checkpoints (by iteration) under ``directory``; the newest ``keep`` are kept (None:
    every one)."""

    def __init__(self, directory: str | Path, keep: int | None = 3):
        self.directory = Path(directory).absolute()
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False),
            item_handlers=ocp.StandardCheckpointHandler(),  # so a fresh manager reads a step's layout
        )

    def save(self, step: int, state) -> None:
        self._manager.save(step, args=ocp.args.StandardSave(_by_path(state)), force=True)
        self._manager.wait_until_finished()

    def latest(self) -> int | None:
        return self._manager.latest_step()

    def steps(self) -> list[int]:
        """The iterations of the checkpoints there, oldest first."""
        return sorted(self._manager.all_steps())

    def restore(self, like, step: int | None = None):
        """The checkpoint ``step`` (default: the newest) in the structure and shardings of ``like``."""
        step = self.latest() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        saved = self._manager.item_metadata(step)
        if saved is not None and all(len(k) == 5 and k.isdigit() for k in saved):
            raw = self._manager.restore(step, args=ocp.args.StandardRestore(_by_index(like)))
            return _rebuilt(like, lambda path, i: raw[f"{i:05d}"])

        def at(path, i):
            node = raw
            for n in path:
                node = node[n]
            return node

        raw = self._manager.restore(step, args=ocp.args.StandardRestore(_by_path(like)))
        return _rebuilt(like, at)

    def restore_fields(self, like, fields: tuple[str, ...], step: int | None = None) -> dict:
        """The attributes ``fields`` of the state saved at ``step`` (default: the newest), each in
        the structure of the same attribute of ``like``; the rest of the saved state (the
        environments, whose layout follows the environment's configuration) may differ from
        ``like``'s. Checkpoints in the flat-index layout restore only into a whole matching state."""
        step = self.latest() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        saved = self._manager.item_metadata(step)
        if saved is not None and all(len(k) == 5 and k.isdigit() for k in saved):
            whole = self.restore(like, step)
            return {f: getattr(whole, f) for f in fields}
        raw = self._manager.restore(step, args=ocp.args.StandardRestore())
        out = {}
        for f in fields:
            if f not in raw:
                raise KeyError(f"the checkpoint at step {step} has no {f!r}")

            def at(path, i, node=raw[f]):
                for n in path:
                    node = node[n]
                return node

            def placed(path, got, want, f=f):
                if got.shape != want.shape:
                    where = "/".join([f, *(_name(e) for e in path)])
                    raise ValueError(f"{where} is {got.shape} there and {want.shape} here")
                return jax.device_put(got, want.sharding) if hasattr(want, "sharding") else got

            like_f = getattr(like, f)
            out[f] = jax.tree_util.tree_map_with_path(placed, _rebuilt(like_f, at), like_f)
        return out

    def restore_intact(self, like, log=lambda *a: None):
        """``(state, step)`` of the newest checkpoint that restores into ``like``; older ones are
        tried when a newer one is damaged (each skip is logged, and the damaged folders are renamed
        ``<step>.damaged`` so that training can save those steps again). :class:`CheckpointError`
        when none restores."""
        steps = sorted(self._manager.all_steps(), reverse=True)
        if not steps:
            raise CheckpointError(f"no checkpoint in {self.directory}")
        reasons = []
        for step in steps:
            try:
                state = self.restore(like, step)
            except Exception as e:  # orbax and tensorstore raise many kinds for a bad file
                reasons.append(f"{step}: {type(e).__name__}")
                log(
                    f"checkpoint {step} in {self.directory} does not restore ({type(e).__name__}); "
                    "trying an older one"
                )
                continue
            if jax.process_index() == 0:
                for bad in steps[: steps.index(step)]:
                    (self.directory / str(bad)).rename(self.directory / f"{bad}.damaged")
            if jax.process_count() > 1:
                from jax.experimental import multihost_utils

                multihost_utils.sync_global_devices("damaged checkpoints set aside")
            self._manager.reload()
            return state, step
        raise CheckpointError(
            f"no checkpoint in {self.directory} restores into this run's configuration ({', '.join(reasons)})"
        )

    def close(self) -> None:
        self._manager.close()
