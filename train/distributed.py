"""Training over several processes (hosts) with JAX's own distributed runtime.

Every process runs the same ``python -m train.run`` with the same options; the environments are
sharded over the devices of all processes (one global mesh, see :class:`train.ppo.Trainer`), the
parameters are replicated, and process 0 writes the run folder (metrics, TensorBoard, curves, README,
export) while all processes take part in the checkpoints. On CPUs the collectives run over gloo.
"""

from __future__ import annotations

import jax
import numpy as np

from train.presets import ConfigError


def initialize(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    auto: bool = False,
) -> None:
    """Joins the cluster: explicitly (``coordinator`` "host:port", ``num_processes``, ``process_id``)
    or, with ``auto``, from what JAX detects (SLURM, Open MPI, Cloud TPU, ...).

    Must run before any other JAX call of the process. :class:`ConfigError` on bad or partial flags,
    or when the coordinator cannot be reached."""
    explicit = (coordinator, num_processes, process_id)
    if auto and any(x is not None for x in explicit):
        raise ConfigError(
            "--distributed detects the cluster; do not combine it with --coordinator and friends"
        )
    if not auto and any(x is None for x in explicit):
        raise ConfigError(
            "multi-process training needs --coordinator, --num-processes and --process-id together"
        )
    if not auto:
        if num_processes < 1 or not 0 <= process_id < num_processes:
            raise ConfigError(
                f"--process-id must be in [0, --num-processes), got {process_id} of {num_processes}"
            )
        host, _, port = coordinator.rpartition(":")
        if not host or not port.isdigit():
            raise ConfigError(f"--coordinator must be host:port, got {coordinator!r}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        if auto:
            jax.distributed.initialize()
        else:
            jax.distributed.initialize(coordinator, num_processes=num_processes, process_id=process_id)
    except (RuntimeError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"jax.distributed could not start: {first}") from None


def is_primary() -> bool:
    """Whether this process writes the run folder (process 0)."""
    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Waits until every process has reached the barrier ``name`` (no-op in one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def agree(flag: bool) -> bool:
    """Process 0's ``flag`` on every process (decisions taken from wall time must be shared)."""
    if jax.process_count() == 1:
        return flag
    from jax.experimental import multihost_utils

    return bool(multihost_utils.broadcast_one_to_all(np.asarray(flag)))
