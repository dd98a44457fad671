"""Benchmarks with peers side by side: ``python -m train.bench [--quick] [--json PATH]``.

Sections (each timed in this one process, on whatever JAX device is default):

* ``lidar``: our analytic ray-caster against ``mjx.ray`` on the same batched scenes (floors of 12
  cylinders, 12 rotated boxes and 4 walls; one 720-ray scan per floor), scans/s and the ratio. The
  two casters' ranges are compared on every scene as well, so the ratio is between equal answers.
* ``floors``: procedural floors generated per second.
* ``robot``: MJX base steps (one 50 Hz control tick each) per second for a fleet.
* ``envs``: ``su`` and ``nav`` environment steps per second (LiDAR, noise, MJX base, users, rewards),
  with 720 rays and with 8 (the LiDAR's share), with the shipped sample trajectories (the replayed
  data does not change the cost).
* ``scaling`` (``--scaling PNG``): ``su`` env steps/s at 256 to 16,384 environments and with 8 to
  64 obstacles per floor, plotted.
* peak host memory (the process's maximum resident set) and, on a GPU, peak device memory (the
  allocator's ``peak_bytes_in_use``), over the whole run.
* ``train``: PPO iterations of the ``su`` preset (Table 4.4: 48 rollouts, 5 epochs x 8 minibatches,
  the 702k-parameter network; ``--quick``: the ``quick`` preset's) at ``--train-envs`` environments,
  ours against Brax's PPO trainer (``train.bench.brax_peer``) and skrl's JAX PPO (``train.bench.skrl_peer``,
  the thesis's trainer library), each on the same environment, network and batch shape:
  transitions per second with the updates included, the figure the thesis's Isaac Lab setup
  reached at about 76,000/s (RTX 4090).

The command exits with status 1 if our ray-caster or our trainer is slower than a peer in this
run, or if the casters disagree: ``--quick`` is the CI check of exactly that.

Timings: each function is compiled and run once (compile time reported separately), then run
``--repeats`` times, alternating ours and the peer; the median is reported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import statistics
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from methd_jax import floors as floors_lib
from methd_jax import lidar, robot
from methd_jax.control import CONTROL_HZ

BENCH_FLOORS = floors_lib.FloorConfig(triangle_fraction=0.0)
"""28 obstacles: 12 cylinders, 12 rotated boxes, 4 walls (boxes, so MJX can batch the scenes)."""
RAY_HEIGHT = 0.5
"""Height of the scan plane in the exported scenes (mid-height of 1 m obstacles)."""


def _timed(fn: Callable, args, repeats: int) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return compile_s, times


def mjx_scenes(batch: floors_lib.Floor):
    """A template MJX model/data and the per-floor geom arrays for ``batch`` (boxes and circles)."""
    first = jax.tree.map(lambda x: x[0], batch)
    C, P, _ = first.capacity
    if not (bool(jnp.all(batch.circle_mask)) and bool(jnp.all(batch.polygon_mask))):
        raise ValueError("MJX scenes need every obstacle slot used (fixed geom count)")
    xml = floors_lib.to_mjcf(first, height=2 * RAY_HEIGHT, circle_geom="capsule")
    m = mujoco.MjModel.from_xml_string(xml)
    if m.ngeom != 1 + C + P or np.any(m.geom_type[1 + C :] != mujoco.mjtGeom.mjGEOM_BOX):
        raise ValueError("MJX scenes need rectangles only (set triangle_fraction=0)")
    mm = mjx.put_model(m)
    dc = mujoco.MjData(m)
    mujoco.mj_forward(m, dc)  # MJX cannot run kinematics on a model with no degrees of freedom
    d = mjx.put_data(m, dc)

    n = batch.circles.shape[0]
    circ = batch.circles
    c_pos = jnp.concatenate([circ[..., :2], jnp.full((n, C, 1), RAY_HEIGHT)], -1)
    c_size = jnp.stack([circ[..., 2], jnp.full((n, C), 4 * RAY_HEIGHT), jnp.zeros((n, C))], -1)
    v = batch.polygons
    e0, e1 = v[:, :, 1] - v[:, :, 0], v[:, :, 2] - v[:, :, 1]
    p_pos = jnp.concatenate([v.mean(2), jnp.full((n, P, 1), RAY_HEIGHT)], -1)
    p_size = jnp.stack(
        [
            0.5 * jnp.linalg.norm(e0, axis=-1),
            0.5 * jnp.linalg.norm(e1, axis=-1),
            jnp.full((n, P), RAY_HEIGHT),
        ],
        -1,
    )
    yaw = jnp.arctan2(e0[..., 1], e0[..., 0])
    c, s, z, o = jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw), jnp.ones_like(yaw)
    p_mat = jnp.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(n, P, 3, 3)
    ground = lambda a: jnp.broadcast_to(a[:1], (n, 1, *a.shape[1:]))  # noqa: E731
    xpos = jnp.concatenate([ground(d.geom_xpos), c_pos, p_pos], 1)
    xmat = jnp.concatenate([ground(d.geom_xmat), jnp.broadcast_to(jnp.eye(3), (n, C, 3, 3)), p_mat], 1)
    size = jnp.concatenate([ground(mm.geom_size), c_size, p_size], 1)
    return mm, d, (size, xpos, xmat)


def make_mjx_scan(mm, d, num_rays: int = lidar.NUM_RAYS, chunk: int | None = None):
    """A jitted ``(size, xpos, xmat, poses) -> ranges`` that casts ``num_rays`` with ``mjx.ray``.

    ``chunk``: floors per ``lax.map`` step. On the 2-core CPU chunks of 4-16 were mjx.ray's fastest
    setting (2.6-2.8k scans/s at 256 floors, against 1.2k for one ``vmap`` over all floors), so the
    default gives the peer that on CPU and a plain ``vmap`` on accelerators.
    """
    if chunk is None:
        chunk = 8 if jax.default_backend() == "cpu" else 0
    angles = 2 * np.pi * np.arange(num_rays) / num_rays
    group = (1, 1, 1, 0, 1, 1)  # skip the ground plane (group 3), as our caster does

    def one(size, xpos, xmat, pose):
        m = mm.replace(geom_size=size)
        dd = d.replace(geom_xpos=xpos, geom_xmat=xmat)
        pnt = jnp.array([pose[0], pose[1], RAY_HEIGHT])
        a = pose[2] + angles
        vecs = jnp.stack([jnp.cos(a), jnp.sin(a), jnp.zeros_like(a)], -1)
        dist = jax.vmap(lambda vec: mjx.ray(m, dd, pnt, vec, geomgroup=group)[0])(vecs)
        return jnp.where(dist < 0, jnp.inf, dist)

    if not chunk:
        return jax.jit(jax.vmap(one))
    return jax.jit(lambda *a: jax.lax.map(lambda x: one(*x), a, batch_size=chunk))


def free_poses(key: jax.Array, batch: floors_lib.Floor, clearance: float = 0.8) -> jax.Array:
    """One random pose per floor whose disc of ``clearance`` is free (rejection sampling, 64 tries)."""

    def one(k, floor):
        k1, k2 = jax.random.split(k)
        lo, hi = floor.bounds[:2], floor.bounds[2:]
        xy = jax.random.uniform(k1, (64, 2), minval=lo, maxval=hi)
        ok = jax.vmap(lambda p: floors_lib.is_free(floor, p, clearance))(xy)
        yaw = jax.random.uniform(k2, (), minval=-jnp.pi, maxval=jnp.pi)
        return jnp.concatenate([xy[jnp.argmax(ok)], yaw[None]])

    n = batch.circles.shape[0]
    return jax.jit(jax.vmap(one))(jax.random.split(key, n), batch)


def bench_lidar(sizes: list[int], repeats: int, log) -> list[dict]:
    rows = []
    ours = jax.jit(jax.vmap(lidar.scan))
    for n in sizes:
        batch = floors_lib.generate_batch(jax.random.key(n), n, BENCH_FLOORS)
        poses = free_poses(jax.random.key(n + 1), batch)
        mm, d, geoms = mjx_scenes(batch)
        peer = make_mjx_scan(mm, d)
        c_ours, _ = _timed(ours, (batch, poses), 0)
        c_peer, _ = _timed(peer, (*geoms, poses), 0)
        t_ours, t_peer = [], []
        for _ in range(repeats):  # alternate, so load changes hit both alike
            t_ours += _timed(ours, (batch, poses), 1)[1]
            t_peer += _timed(peer, (*geoms, poses), 1)[1]
        a = np.minimum(np.asarray(ours(batch, poses)), 30.0)
        b = np.minimum(np.asarray(peer(*geoms, poses)), 30.0)
        row = {
            "floors": n,
            "ours_scans_per_s": n / statistics.median(t_ours),
            "mjx_ray_scans_per_s": n / statistics.median(t_peer),
            "ours_compile_s": c_ours,
            "mjx_ray_compile_s": c_peer,
            "max_abs_diff_m": float(np.max(np.abs(a - b))),
            # mjx.ray computes in float32 with cancellation on grazing capsule/box hits; the odd
            # ray that differs was checked against MuJoCo's float64 mj_ray, which agrees with ours.
            "rays_agreeing_1mm": float(np.mean(np.abs(a - b) <= 1e-3)),
        }
        row["ratio"] = row["ours_scans_per_s"] / row["mjx_ray_scans_per_s"]
        log(
            f"  lidar  {n:>6} floors: ours {row['ours_scans_per_s']:>10,.0f} scans/s   "
            f"mjx.ray {row['mjx_ray_scans_per_s']:>9,.0f} scans/s   ratio {row['ratio']:5.1f}x   "
            f"agree {100 * row['rays_agreeing_1mm']:.3f}%"
        )
        rows.append(row)
    return rows


def bench_floors(n: int, repeats: int, log) -> dict:
    gen = lambda k: floors_lib.generate_batch(k, n)  # noqa: E731  (jitted inside)
    c, times = _timed(gen, (jax.random.key(0),), repeats)
    row = {"floors": n, "floors_per_s": n / statistics.median(times), "compile_s": c}
    log(f"  floors {n:>6} per call: {row['floors_per_s']:>10,.0f} floors/s")
    return row


def bench_robot(n: int, repeats: int, log) -> dict:
    base = robot.Robot()
    data = jax.vmap(base.init)(jnp.zeros((n, 3)))
    cmd = jnp.tile(jnp.array([1.0, 0.5, 0.3]), (n, 1))
    step = jax.jit(jax.vmap(base.step))
    c, times = _timed(step, (data, cmd), repeats)
    row = {
        "robots": n,
        "robot_steps_per_s": n / statistics.median(times),
        "compile_s": c,
        "substeps": base.substeps,
    }
    log(f"  robot  {n:>6} robots: {row['robot_steps_per_s']:>10,.0f} robot-steps/s (50 Hz ticks)")
    return row


def bench_envs(sizes: list[int], repeats: int, log) -> list[dict]:
    """``su`` and ``nav`` env steps/s with the 720-ray LiDAR and with 8 rays (the fewest an env
    takes: the LiDAR all but off), so that the LiDAR's share of a step is visible."""
    import envs

    rows = []
    for name in ("su", "nav"):
        for rays in (720, 8):
            env = envs.make(name, motion="sample", num_rays=rays)
            reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
            for n in sizes:
                state = reset(jax.random.split(jax.random.key(n), n))
                action = jnp.zeros((n, env.action_size))
                c, times = _timed(step, (state, action), repeats)
                rate = n / statistics.median(times)
                rows.append({"env": name, "rays": rays, "envs": n, "env_steps_per_s": rate, "compile_s": c})
                log(f"  env    {name:>4} {n:>6} envs, {rays:>3} rays: {rate:>10,.0f} env-steps/s")
    return rows


def bench_scaling(env_counts: list[int], obstacle_counts: list[int], repeats: int, log) -> dict:
    """``su`` env steps per second against the number of environments (default floors) and against
    the number of obstacles per floor (half cylinders, half boxes/triangles, plus 4 walls) at the
    largest count that fits 2,048 environments."""
    import envs
    from envs.nav import ENV_FLOORS

    def rate(n: int, **overrides) -> float:
        env = envs.make("su", motion="sample", **overrides)
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(n), n))
        step = jax.jit(jax.vmap(env.step))
        _, times = _timed(step, (state, jnp.zeros((n, env.action_size))), repeats)
        return n / statistics.median(times)

    by_envs = []
    for n in env_counts:
        by_envs.append({"envs": n, "env_steps_per_s": rate(n)})
        log(f"  scale  su {n:>6} envs:            {by_envs[-1]['env_steps_per_s']:>10,.0f} env-steps/s")
    n = min(2048, max(env_counts))
    by_obstacles = []
    for k in obstacle_counts:
        floor = dataclasses.replace(
            ENV_FLOORS, num_circles=(k // 2, k // 2), num_polygons=(k - k // 2, k - k // 2)
        )
        by_obstacles.append({"obstacles": k, "envs": n, "env_steps_per_s": rate(n, floor=floor)})
        log(
            f"  scale  su {n:>6} envs, {k:>3} obstacles: "
            f"{by_obstacles[-1]['env_steps_per_s']:>10,.0f} env-steps/s"
        )
    return {"by_envs": by_envs, "by_obstacles": by_obstacles}


def plot_scaling(scaling: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    e = scaling["by_envs"]
    a.plot([r["envs"] for r in e], [r["env_steps_per_s"] for r in e], "o-")
    a.set_xscale("log", base=2)
    a.set_xlabel("environments")
    a.set_ylabel("su env-steps/s")
    o = scaling["by_obstacles"]
    b.plot([r["obstacles"] for r in o], [r["env_steps_per_s"] for r in o], "o-")
    b.set_xlabel(f"obstacles per floor (+4 walls), {o[0]['envs'] if o else 0} envs")
    for ax in (a, b):
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    fig.suptitle(f"How cost grows ({machine()['device']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def bench_train(num_envs: int, iterations: int, repeats: int, log, preset_name: str = "su") -> dict:
    """Our PPO against Brax's and skrl's on a preset's environment, network and batch shape (the
    thesis's ``su`` by default; ``--quick`` uses the ``quick`` preset's small network, which
    compiles in a fraction of the time).

    Each side runs ``iterations`` PPO iterations per timed call (one ``lax.scan`` for ours, one
    Brax "training epoch" for Brax's, ``iterations`` calls of skrl's trainer for skrl's) and the
    median of ``repeats`` steady-state calls is reported; the extra time of the first call is the
    compile time. Our calls are interleaved with the peers' (one after each Brax epoch, from
    Brax's progress callback, which its own timing leaves out, and one after each skrl
    iteration), so a burst of load from elsewhere on a shared machine slows both sides of a ratio
    alike instead of whichever happened to run then. Each compiles once: ``train.bench.brax_peer`` and
    ``train.bench.skrl_peer`` hand the peers their state laid out as their own outputs will be (before
    that, Brax's first epoch and skrl's environment step and models compiled twice, ~15 s and
    ~10 s more on 2 CPU cores). Transitions/s include the updates."""
    from brax.training.agents.ppo import train as brax_ppo

    from train.bench import brax_peer, skrl_peer
    from train.presets import apply_overrides, preset
    from train.run import build

    config = apply_overrides(preset(preset_name), ["env.motion=sample", f"num_envs={num_envs}"])
    setup = build(config)
    trainer, cfg = setup.trainer, config.ppo
    per = trainer.transitions_per_iteration
    episode_length = round(config.env.time_limit * CONTROL_HZ)
    run = jax.jit(trainer.run, static_argnums=1)
    state = jax.jit(trainer.init)(jax.random.key(0))
    first, _ = _timed(lambda s: run(s, iterations)[1], (state,), 0)
    ours: dict[str, list[float]] = {"brax": [], "skrl": []}  # our steady calls beside each peer's

    def ours_once(peer: str) -> None:
        t0 = time.perf_counter()
        jax.block_until_ready(run(state, iterations)[1])
        ours[peer].append(time.perf_counter() - t0)

    brax_peer.patch_jax_for_brax()
    epochs: list[float] = []  # Brax's own per-epoch wall times (it times each training epoch)
    walltime = [0.0]

    def progress(_, metrics):
        epochs.append(float(metrics["training/walltime"]) - walltime[0])
        walltime[0] = float(metrics["training/walltime"])
        ours_once("brax")

    brax_ppo.train(
        environment=setup.env,
        num_timesteps=(repeats + 1) * iterations * per,
        num_evals=repeats + 2,  # one epoch of `iterations` training steps between progress calls
        run_evals=False,
        episode_length=episode_length,
        num_envs=num_envs,
        unroll_length=cfg.rollouts,
        batch_size=num_envs // cfg.minibatches,
        num_minibatches=cfg.minibatches,
        num_updates_per_batch=cfg.epochs,
        learning_rate=cfg.learning_rate,
        entropy_cost=cfg.entropy_scale,
        discounting=cfg.gamma,
        gae_lambda=cfg.lam,
        clipping_epsilon=cfg.ratio_clip,
        max_grad_norm=cfg.grad_norm_clip,
        normalize_observations=True,
        network_factory=brax_peer.network_factory(setup.network_spec),
        seed=0,
        progress_fn=progress,
    )
    brax_s = statistics.median(epochs[1:])
    ours_s = statistics.median(ours["brax"])

    row = {
        "preset": preset_name,
        "envs": num_envs,
        "transitions_per_iteration": per,
        "iterations_per_call": iterations,
        "repeats": repeats,
        "ours_transitions_per_s": iterations * per / ours_s,
        "brax_transitions_per_s": iterations * per / brax_s,
        "ours_compile_s": max(first - ours_s, 0.0),
        "brax_compile_s": max(epochs[0] - brax_s, 0.0),
    }
    row["ratio_brax"] = row["ours_transitions_per_s"] / row["brax_transitions_per_s"]
    if skrl_peer.available():
        skrl = skrl_peer.make(setup.env, setup.network_spec, cfg, num_envs, episode_length)
        before = {role: skrl.head(role) for role in ("policy", "value")}
        skrl_times = []
        for _ in range(repeats + 1):
            skrl_times.append(sum(skrl.iteration() for _ in range(iterations)))
            ours_once("skrl")
        # a misconfigured skrl (say, an update never reached) would look fast: check both heads learned
        updated = all(bool(jnp.any(before[role] != skrl.head(role))) for role in before)
        skrl_s = statistics.median(skrl_times[1:])
        row["skrl_transitions_per_s"] = iterations * per / skrl_s
        row["skrl_compile_s"] = max(skrl_times[0] - skrl_s, 0.0)
        row["skrl_updated_both_heads"] = updated
        # all our steady calls, those beside Brax's epochs and those beside skrl's iterations
        ours_s = statistics.median(ours["brax"] + ours["skrl"])
        row["ours_transitions_per_s"] = iterations * per / ours_s
        row["ratio_brax"] = row["ours_transitions_per_s"] / row["brax_transitions_per_s"]
        row["ratio_skrl"] = row["ours_transitions_per_s"] / row["skrl_transitions_per_s"]
        skrl_text = (
            f"skrl PPO {row['skrl_transitions_per_s']:>9,.0f} ({row['ratio_skrl']:.1f}x)   "
            f"(updates included; compile {row['ours_compile_s']:.0f} s / {row['brax_compile_s']:.0f} s / "
            f"{row['skrl_compile_s']:.0f} s)"
        )
    else:
        row["skrl_missing"] = skrl_peer.MISSING
        skrl_text = f"skrl PPO: {skrl_peer.MISSING}, its column is left out"
    log(
        f"  train {preset_name:>5} {num_envs:>6} envs: "
        f"ours {row['ours_transitions_per_s']:>9,.0f} transitions/s   "
        f"Brax PPO {row['brax_transitions_per_s']:>9,.0f} ({row['ratio_brax']:.1f}x)   {skrl_text}"
    )
    return row


def bench_loop(num_envs: int, repeats: int, log, preset_name: str = "quick") -> dict:
    """The run loop's call shape: ``train.run.CHUNK`` iterations as that many jitted
    ``Trainer.update`` calls (the loop before 2026-11-28) against one ``Trainer.run_upto`` call
    with the state donated (the loop now), interleaved, median of ``repeats`` each, metrics
    fetched to the host after each call as the loop does."""
    from train.presets import apply_overrides, preset
    from train.run import CHUNK, build

    config = apply_overrides(preset(preset_name), ["env.motion=sample", f"num_envs={num_envs}"])
    trainer = build(config).trainer
    update = jax.jit(trainer.update)
    chunk = jax.jit(trainer.run_upto, static_argnums=2, donate_argnums=0)
    state = {"calls": jax.jit(trainer.init)(jax.random.key(0))}
    state["chunk"] = jax.jit(trainer.init)(jax.random.key(0))

    def per_call():
        s = state["calls"]
        for _ in range(CHUNK):
            s, m = update(s)
            jax.device_get(m)
        state["calls"] = s

    def one_chunk():
        state["chunk"], m = chunk(state["chunk"], jnp.int32(CHUNK), CHUNK)
        jax.device_get(m)

    times: dict[str, list[float]] = {"calls": [], "chunk": []}
    per_call(), one_chunk()  # compile
    for _ in range(repeats):
        for name, fn in (("calls", per_call), ("chunk", one_chunk)):
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    per = trainer.transitions_per_iteration * CHUNK
    row = {
        "preset": preset_name,
        "envs": num_envs,
        "iterations_per_call": CHUNK,
        "per_iteration_calls_transitions_per_s": per / statistics.median(times["calls"]),
        "chunked_donated_transitions_per_s": per / statistics.median(times["chunk"]),
    }
    row["ratio"] = row["chunked_donated_transitions_per_s"] / row["per_iteration_calls_transitions_per_s"]
    log(
        f"  loop  {preset_name:>5} {num_envs:>6} envs: {CHUNK} calls of one iteration "
        f"{row['per_iteration_calls_transitions_per_s']:>9,.0f} transitions/s   one call of {CHUNK}, donated "
        f"{row['chunked_donated_transitions_per_s']:>9,.0f} ({row['ratio']:.2f}x)"
    )
    return row


def peak_device_memory_mb(devices=None) -> float | None:
    """The largest ``peak_bytes_in_use`` over the local devices since the process started, in MB;
    None where the backend keeps no allocator statistics (the CPU)."""
    peaks = []
    for dev in devices if devices is not None else jax.local_devices():
        stats = dev.memory_stats()
        if stats and "peak_bytes_in_use" in stats:
            peaks.append(stats["peak_bytes_in_use"] / 2**20)
    return max(peaks) if peaks else None


def machine() -> dict:
    dev = jax.devices()[0]
    return {
        "device": f"{dev.platform}:{getattr(dev, 'device_kind', '')}",
        "device_count": jax.device_count(),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
        "date": time.strftime("%Y-%m-%d"),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m train.bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="the peer checks only (LiDAR vs mjx.ray, PPO vs Brax and skrl), small batches, few repeats (CI)",
    )
    p.add_argument("--sizes", type=int, nargs="+", help="floor batch sizes for the LiDAR section")
    p.add_argument("--robots", type=int, help="fleet size for the robot section (default 4096)")
    p.add_argument("--env-sizes", type=int, nargs="+", help="batch sizes for the environment section")
    p.add_argument("--train-envs", type=int, help="environments for the training section (default 2048)")
    p.add_argument("--repeats", type=int, help="timed runs per measurement")
    p.add_argument("--json", help="also write the results as JSON to this path")
    p.add_argument(
        "--scaling",
        metavar="PNG",
        help="also measure su env-steps/s at 256-16384 environments and 8-64 obstacles; plot to PNG",
    )
    p.add_argument(
        "--device-budget",
        type=float,
        metavar="SECONDS",
        help="the accelerator figures of docs/benchmarks.md (LiDAR vs mjx.ray at 4,096 and 16,384 floors; "
        "su and nav at 2,048-32,768 envs; PPO su at 2,048 envs vs Brax and skrl; quick) in that order "
        "until SECONDS are spent; writes --json (default bench.json) and its table rows (.md)",
    )
    args = p.parse_args(argv)
    if args.device_budget is not None:
        if not args.device_budget > 0:
            p.error("--device-budget must be positive")
        return device_run(args)
    sizes = args.sizes or ([64] if args.quick else [64, 1024, 4096])
    robots = args.robots or (256 if args.quick else 4096)
    env_sizes = args.env_sizes or ([64] if args.quick else [256, 2048, 8192])
    train_envs = args.train_envs or (64 if args.quick else 2048)
    repeats = args.repeats or (2 if args.quick else 7)
    if min(sizes) < 1 or robots < 1 or repeats < 1 or min(env_sizes) < 1 or train_envs < 1:
        p.error("--sizes, --env-sizes, --robots, --train-envs and --repeats must be positive")

    def log(msg):
        print(msg, flush=True)

    info = machine()
    log(
        f"methd-jax bench on {info['device']} ({info['cpu_count']} CPUs), jax {info['jax']}, "
        f"mujoco {info['mujoco']}"
    )
    results = {"machine": info, "lidar": bench_lidar(sizes, repeats, log)}
    if not args.quick:  # --quick: the two sections with a peer to check against, nothing else
        results["floors"] = bench_floors(max(sizes), repeats, log)
        results["robot"] = bench_robot(robots, repeats, log)
        results["envs"] = bench_envs(env_sizes, repeats, log)
    # a PPO iteration at the full batch is long: 3 repeats; --quick's iterations take a fraction
    # of a second, and 5 interleaved repeats keep one slow call from deciding the CI check
    results["train"] = bench_train(
        train_envs,
        1 if args.quick else 2,
        (args.repeats or 5) if args.quick else min(repeats, 3),
        log,
        "quick" if args.quick else "su",
    )
    if not args.quick:
        results["loop"] = bench_loop(256, min(repeats, 5), log)
    if args.scaling:
        results["scaling"] = bench_scaling([256, 1024, 4096, 16384], [8, 16, 32, 64], repeats, log)
        plot_scaling(results["scaling"], args.scaling)
        log(f"  scaling plot written to {args.scaling}")
    results["peak_host_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    device_peak = results["peak_device_memory_mb"] = peak_device_memory_mb()
    device_text = (
        f"{device_peak:.0f} MB" if device_peak is not None else f"n/a ({jax.default_backend()} reports none)"
    )
    log(f"  peak host memory {results['peak_host_memory_mb']:.0f} MB, peak device memory {device_text}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
        log(f"results written to {args.json}")
    failures = checks(results)
    for failure in failures:
        log(f"FAILED: {failure}")
    return 1 if failures else 0


def device_plan(args) -> list[tuple[str, Callable]]:
    """The sections of ``--device-budget``, most wanted first; ``--sizes``, ``--env-sizes``,
    ``--train-envs`` and ``--repeats`` shrink them (the CPU test)."""
    sizes = args.sizes or [4096, 16384]
    env_sizes = args.env_sizes or [2048, 8192, 32768]
    train_envs = args.train_envs or 2048
    repeats = args.repeats or 5
    return [
        ("lidar", lambda log: bench_lidar(sizes, repeats, log)),
        ("train", lambda log: bench_train(train_envs, 2, min(repeats, 3), log, "su")),
        ("envs", lambda log: bench_envs(env_sizes, repeats, log)),
        ("train_quick", lambda log: bench_train(args.train_envs or 256, 2, min(repeats, 3), log, "quick")),
    ]


def device_run(args) -> int:
    """``--device-budget``: each section of :func:`device_plan` starts only while the budget lasts
    (a section that has started runs to its end) and is otherwise recorded as skipped; then the
    peak memory, the JSON and the table rows."""
    budget, t0 = args.device_budget, time.perf_counter()
    info = machine()
    print(f"methd-jax device bench on {info['device']}, jax {info['jax']}, budget {budget:g} s", flush=True)
    results: dict = {"machine": info, "budget_s": budget, "skipped": {}}
    for name, section in device_plan(args):
        spent = time.perf_counter() - t0
        if spent >= budget:
            results["skipped"][name] = f"budget spent ({spent:.0f} of {budget:g} s) before it started"
            print(f"  {name}: skipped, {results['skipped'][name]}", flush=True)
            continue
        results[name] = section(lambda msg: print(msg, flush=True))
        results.setdefault("section_s", {})[name] = time.perf_counter() - t0 - spent
    results["peak_host_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    results["peak_device_memory_mb"] = peak_device_memory_mb()
    results["wall_s"] = time.perf_counter() - t0
    out = args.json or "bench.json"
    with open(out, "w") as f:
        json.dump(results, f, indent=2)
    rows = markdown_rows(results)
    md = os.path.splitext(out)[0] + ".md"
    with open(md, "w") as f:
        f.write(rows)
    print(rows + f"\nresults written to {out} and {md} ({results['wall_s']:.0f} s)", flush=True)
    return 0


def markdown_rows(results: dict) -> str:
    """The rows ``docs/benchmarks.md`` takes from a ``--device-budget`` run."""
    device = results["machine"]["device"]
    lines = [f"Device: {device}; jax {results['machine']['jax']}; {results['machine']['date']}", ""]
    lines += ["| measurement | ours | peer | ratio |", "|---|---|---|---|"]
    for r in results.get("lidar", []):
        lines.append(
            f"| LiDAR, {r['floors']:,} floors x 720 rays, scans/s | {r['ours_scans_per_s']:,.0f} "
            f"| mjx.ray {r['mjx_ray_scans_per_s']:,.0f} | {r['ratio']:.1f}x |"
        )
    for key in ("train", "train_quick"):
        t = results.get(key)
        if t:
            for peer, name in (("brax", "Brax PPO"), ("skrl", "skrl PPO")):
                if f"ratio_{peer}" not in t:
                    lines.append(
                        f"| PPO `{t['preset']}`: {name} | | {t.get(f'{peer}_missing', 'not run')} | |"
                    )
                    continue
                lines.append(
                    f"| PPO `{t['preset']}`, {t['envs']:,} envs, transitions/s (updates included) "
                    f"| {t['ours_transitions_per_s']:,.0f} | {name} {t[f'{peer}_transitions_per_s']:,.0f} "
                    f"| {t[f'ratio_{peer}']:.1f}x |"
                )
    for r in results.get("envs", []):
        what = f"`{r['env']}` env steps/s, {r['envs']:,} envs, {r['rays']} rays"
        lines.append(f"| {what} | {r['env_steps_per_s']:,.0f} | | |")
    peak = results.get("peak_device_memory_mb")
    lines.append(
        f"| peak device memory, MB | {peak:,.0f} | | |"
        if peak is not None
        else "| peak device memory | n/a | | |"
    )
    for name, why in results.get("skipped", {}).items():
        lines.append(f"| {name} | skipped: {why} | | |")
    return "\n".join(lines) + "\n"


def checks(results: dict) -> list[str]:
    """What must hold on any machine: equal answers from the casters, and ours no slower than
    either peer measured in this process (ratios, not absolute times)."""
    out = []
    for r in results["lidar"]:
        if r["rays_agreeing_1mm"] < 0.999:
            out.append(
                f"only {100 * r['rays_agreeing_1mm']:.2f}% of rays agree with mjx.ray at {r['floors']} floors"
            )
        if r["ratio"] < 1.0:
            out.append(f"our ray-caster is slower than mjx.ray at {r['floors']} floors ({r['ratio']:.2f}x)")
    train = results["train"]
    for peer, name in (("brax", "Brax's"), ("skrl", "skrl's")):
        ratio = train.get(f"ratio_{peer}")
        if ratio is not None and ratio < 1.0:
            out.append(f"our PPO is slower than {name} at {train['envs']} environments ({ratio:.2f}x)")
    return out
