"""Orbax checkpoints of a whole :class:`train.ppo.TrainState`.

The environments' state is saved with the parameters, optimiser state, normaliser statistics,
iteration and key, so a resumed run continues exactly where it stopped (bit-identical on CPU).
Orbax saves neither typed PRNG keys nor empty arrays (MJX keeps a few, such as ``act`` of a model
without actuator states), so the state is saved as a flat dict of its non-empty leaves, keys as
their raw data, and rebuilt from a state of the same structure on restore.
"""

from __future__ import annotations

from pathlib import Path

import jax
import orbax.checkpoint as ocp


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _flat(tree) -> dict:
    leaves = jax.tree.leaves(tree)
    return {f"{i:05d}": jax.random.key_data(x) if _is_key(x) else x for i, x in enumerate(leaves) if x.size}


class CheckpointError(ValueError):
    """No checkpoint of a run folder can be restored (the message says which were tried)."""


class Checkpoints:
    """Numbered checkpoints (by iteration) under ``directory``; the newest ``keep`` are kept."""

    def __init__(self, directory: str | Path, keep: int = 3):
        self.directory = Path(directory).absolute()
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False),
        )

    def save(self, step: int, state) -> None:
        self._manager.save(step, args=ocp.args.StandardSave(_flat(state)), force=True)
        self._manager.wait_until_finished()

    def latest(self) -> int | None:
        return self._manager.latest_step()

    def restore(self, like, step: int | None = None):
        """The checkpoint ``step`` (default: the newest) in the structure and shardings of ``like``."""
        step = self.latest() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        raw = self._manager.restore(step, args=ocp.args.StandardRestore(_flat(like)))
        leaves, treedef = jax.tree.flatten(like)
        for i, x in enumerate(leaves):
            if x.size:
                r = raw[f"{i:05d}"]
                leaves[i] = jax.random.wrap_key_data(r, impl=jax.random.key_impl(x)) if _is_key(x) else r
        return jax.tree.unflatten(treedef, leaves)

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
