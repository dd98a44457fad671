"""``python -m train.evaluate``: the thesis's Table 5.1 for the baselines and trained policies.

SU: Static, Heuristic and (with ``--su RUN``) the trained single-user policy, each through the
held-out trajectories in sequence on the lab floor. MU: Static and (with ``--mu RUN``) NavRL with
its GuideRL policy, one reset per trajectory pair. Prints Table 5.1 with the thesis's numbers
beside ours and the statistics; writes ``table.md``, ``results.json`` (summaries, statistics and
every episode's numbers) and the figures 5.3-5.6 as PNG into the output folder.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from envs import guide as guide_env
from envs import tasks
from envs.evaluation import Policy
from envs.nav import load_bank
from methd_jax import floors, lidar
from methd_jax import robot as robot_lib
from methd_jax.cli import OneLineParser
from methd_jax.control import CONTROL_HZ
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.evaluation import engine as eng
from methd_jax.evaluation import methods, metrics, plots, stats
from methd_jax.floors import FloorConfig
from methd_jax.geometry import KAIROS
from methd_jax.motion import MotionDataError
from methd_jax.motion.dataset import progress_bar
from methd_jax.motion.features import HipConfig
from train import export
from train import run as run_lib
from train.presets import PRETRAINED, ConfigError

SAFETY_ROW = "DRL + safety"
"""The row of a policy with the deployment's safety layer between it and the base."""


def shipped(kind: str) -> Path | None:
    """The shipped policy folder of ``kind`` ("su", "guide", "nav"), or None if it is not there."""
    folder = PRETRAINED / kind
    return folder if (folder / "manifest.json").is_file() else None


def load_policy(
    run: str | Path, bank, kind: str, guide: str | Path | None = None, safety: SafetyConfig | None = None
) -> Policy:
    """A trained policy from a run folder or an exported policy folder, as an evaluation method.

    ``kind`` is "su" (a single-user policy) or "nav" (NavRL; its GuideRL policy comes from ``guide``
    or from where the policy's manifest records it). ``safety``: with the deployment's safety layer."""
    want = {"su": "--su takes a single-user (su) run", "nav": "--mu takes a NavRL (nav) run"}[kind]
    policy = _load(run, kind, want)
    task = tasks.get(kind)
    folders = _dependencies(run, {"guide": str(guide)} if guide and "guide" in task.depends else None)
    missing = sorted(set(task.depends) - set(folders))  # the MU procedure needs GuideRL's goal
    if missing:
        raise ConfigError(
            f"{run} was trained without a {missing[0]} policy (scripted goals); pass one as --{missing[0]}"
        )
    policies = run_lib.load_dependencies(folders, str(run))
    env = task.build(task.config_from(policy.manifest["env_config"]), bank=bank, policies=policies)
    return Policy(env, policy, name=SAFETY_ROW if safety else "DRL", safety=safety)


def procedural(
    run: str | Path, episodes: int = 200, *, seed: int = 1, floor: FloorConfig | None = None
) -> dict[str, float]:
    """A single-user policy on ``episodes`` fresh procedural floors (never the lab twin), users on the
    held-out test trajectories, each episode run to its end as in training (collision, success or
    the time limit). ``floor``: the floor distribution (default: the policy's own training floors);
    the floors come from ``seed``'s keys, which training never draws (it splits its own seed's key).
    Returns the share of episodes that ended in each way and their count.

    An obstacle collision is the lab evaluation's: the footprint against a dense scan of
    ``EngineConfig.collision_rays`` rays, no margin. Training's own test (the policy's few rays plus
    its ``collision_margin``) is stricter by design and would count near misses."""
    policy = _load(run, "su", "--procedural takes a su policy")
    trained = tasks.get("su").config_from(policy.manifest["env_config"])
    return procedural_outcomes(trained, policy, episodes, seed=seed, floor=floor)


def procedural_config(trained, floor: FloorConfig | None = None):
    """The ``su`` config of :func:`procedural`'s episodes for a policy trained with ``trained``:
    its floors (or ``floor``) but never the lab twin, the test trajectories, no collision margin,
    the uniform spawn whatever share of starts beside obstacles training drew, and the episode
    ending at its first contact however many training let it go on through."""
    return dataclasses.replace(
        trained,
        lab=False,
        lab_fraction=0.0,
        split="test",
        floor=floor or trained.floor,
        safety=dataclasses.replace(trained.safety, collision_margin=0.0),
        spawn_near=(0.0, trained.spawn_near[1]),
        contact_limit=1,
    )


def procedural_outcomes(
    trained, policy, episodes: int, *, seed: int = 1, floor: FloorConfig | None = None
) -> dict[str, float]:
    """:func:`procedural` for a policy ``obs -> action`` trained with the ``su`` config ``trained``."""
    config = procedural_config(trained, floor)
    env = tasks.get("su").build(config)
    steps = round(config.time_limit * CONTROL_HZ)
    rays = eng.EngineConfig().collision_rays
    boundary = jnp.asarray(KAIROS.ray_geometry(rays)[0])

    outcomes = ("obstacle", "user", "success", "timeout")

    def one(state, ended, outcome):
        """One step of one episode; ``outcome`` keeps how it ended the first time it did."""
        state = env.step(state, jnp.clip(policy(state.obs), -1.0, 1.0))
        w = state.pipeline_state
        contact = jnp.any(lidar.scan(w.floor, robot_lib.pose(w.robot), num_rays=rays) < boundary)
        m = state.metrics
        now = jnp.stack(
            [m["collision_obstacle"], m["collision_user"], m["success"], state.info["truncation"]]
        )
        now = jnp.where(contact, jnp.array([1.0, 0.0, 0.0, 0.0]), now)
        over = (state.done > 0) | contact
        return state, ended | over, jnp.where(over & ~ended, now, outcome)

    @jax.jit
    def run_all(keys):
        carry = (jax.vmap(env.reset)(keys), jnp.zeros(episodes, bool), jnp.zeros((episodes, len(outcomes))))
        carry, _ = jax.lax.scan(lambda c, _: (jax.vmap(one)(*c), None), carry, None, steps)
        return carry[1], carry[2]

    ended, outcome = jax.device_get(run_all(jax.random.split(jax.random.key(seed), episodes)))
    out = {name: float(np.mean(outcome[:, i])) for i, name in enumerate(outcomes)}
    out["episodes"] = episodes
    out["unfinished"] = float(np.mean(~ended))
    return out


def _dependencies(run: str | Path, given: dict[str, str] | None = None) -> dict[str, str]:
    """The policies ``run`` was trained with, as its manifest records them unless ``given``
    (:class:`ConfigError` when a recorded one is gone)."""
    try:
        return export.dependencies(run, given)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(str(err)) from None


def evaluate(
    su: dict,
    mu: dict,
    bank,
    floor,
    *,
    mu_offset: int = 50,
    seed: int = 0,
    config: eng.EngineConfig | None = None,
    progress: bool = True,
) -> dict[str, dict[str, np.ndarray]]:
    """Runs every method; ``su`` / ``mu`` map names to methods. Returns name -> per-episode results
    (names prefixed "SU " / "MU ")."""
    out = {}
    key = jax.random.key(seed)
    for scenario, chosen in (("SU", su), ("MU", mu)):
        for name, method in chosen.items():
            engine = eng.Engine(method, bank, floor, config or eng.EngineConfig())
            starts = eng.start_poses(floor, engine.grid)
            if scenario == "SU":
                schedule = eng.su_schedule(bank, starts)
            else:
                schedule = eng.mu_schedule(bank, starts, mu_offset)
            bar = progress_bar(f"{scenario} {name}", progress)
            t0 = time.perf_counter()
            out[f"{scenario} {name}"] = engine.run(schedule, key, progress=bar)
            if progress:
                print(f"{scenario} {name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return out


def statistics(results: dict[str, dict[str, np.ndarray]]) -> dict:
    """Friedman + Kendall's W (>= 3 methods) and Holm-corrected pairwise Wilcoxon, per scenario."""
    out = {}
    for scenario in ("SU", "MU"):
        names = [n for n in results if n.startswith(scenario + " ")]
        if len(names) < 2:
            continue
        block = {}
        for key in ("t_pos", "distance_to_hip"):
            samples = {n: results[n][key] for n in names}
            entry = {"pairwise": stats.pairwise(samples)}
            if len(names) >= 3:
                entry["friedman"] = stats.friedman(samples)
            block[key] = entry
        out[scenario] = block
    return out


def _stats_text(st: dict) -> str:
    lines = []
    for scenario, block in st.items():
        for key, entry in block.items():
            if "friedman" in entry:
                f = entry["friedman"]
                lines.append(
                    f"{scenario} {key}: Friedman chi2({f['df']}) = {f['chi2']:.1f}, p = {f['p']:.2g}, "
                    f"Kendall's W = {f['kendall_w']:.3f} (N = {f['n']})"
                )
            for row in entry["pairwise"]:
                lines.append(
                    f"{scenario} {key}: {row['a']} vs {row['b']}: Z = {row['z']:.2f}, p(Holm) = "
                    f"{row['p_holm']:.2g}, r = {row['r']:.2f} (N = {row['n']})"
                )
    return "\n".join(lines)


def _json(value):
    if isinstance(value, dict):
        return {k: _json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_json(v) for v in value.tolist()]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def write_report(results: dict, out: Path, meta: dict) -> tuple[str, dict]:
    """``table.md``, ``results.json`` and the figures; returns the table and the statistics."""
    out.mkdir(parents=True, exist_ok=True)
    summaries = {name: metrics.summary(r) for name, r in results.items()}
    # GuideRL alone (--no-su --no-mu --guide RUN) leaves no rows: its accuracy is the report
    table = metrics.table_markdown(summaries) if summaries else ""
    st = statistics(results)
    stats_text = _stats_text(st)
    figures = plots.figures(results, summaries, out) if summaries else []
    text = ["# Table 5.1, reproduced", "", _meta_text(meta), "", *([table, ""] if table else [])]
    if "procedural" in meta:
        text += [_procedural_text(meta["procedural"]), ""]
    if "guide" in meta:
        text += [_guide_text(meta["guide"], meta.get("split", "test")), ""]
    if stats_text:
        text += ["## Statistics", "", "```", stats_text, "```", ""]
    if figures:
        text += ["Figures: " + ", ".join(f"[{p.name}]({p.name})" for p in figures), ""]
    (out / "table.md").write_text("\n".join(text))
    payload = {"meta": meta, "summaries": summaries, "statistics": st, "thesis": metrics.THESIS}
    if "guide" in meta:
        payload["guide"] = meta["guide"]
    payload["episodes"] = results
    (out / "results.json").write_text(json.dumps(_json(payload), indent=1) + "\n")
    return table, st


def _procedural_text(p: dict) -> str:
    return (
        f"SU DRL on {p['episodes']} fresh procedural floors with obstacles: episodes ended by an obstacle "
        f"collision {100 * p['obstacle']:.1f}%, a user collision {100 * p['user']:.1f}%, success "
        f"{100 * p['success']:.1f}%, the time limit {100 * p['timeout']:.1f}%"
    )


def load_guide(run: str | Path) -> export.Policy:
    """The GuideRL policy of a run folder or exported policy folder; :class:`ConfigError` otherwise."""
    return _load(run, "guide", "--guide takes a GuideRL (guide) run")


def _load(run: str | Path, kind: str, want: str) -> export.Policy:
    """The exported policy of ``run`` if it is a ``kind`` policy; else :class:`ConfigError` ending
    in ``want``."""
    try:
        policy = export.load(run)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(str(err)) from None
    if policy.manifest["env"] != kind:
        raise ConfigError(f"{run} holds a {policy.manifest['env']!r} policy; {want}")
    return policy


def guide_accuracy(run: str | Path, bank) -> dict:
    """GuideRL's accuracy on every ordered pair of ``bank``'s trajectories whose requests differ
    (see :func:`envs.guide.pair_accuracy`) at the request and ``EARLY`` s before it (how early
    the goal a NavRL policy drives to is right): ``{"accuracy": fraction, "pairs": count,
    "accuracy_early": fraction, "early_s": EARLY}``."""
    policy = load_guide(run)
    if len(guide_env.held_out_pairs(bank)) == 0:
        raise ConfigError("GuideRL's accuracy needs two trajectories whose requests differ")
    at, early = guide_env.pair_correct(policy, bank, lead=(0.0, EARLY))
    return {
        "accuracy": float(at.mean()),
        "pairs": len(at),
        "accuracy_early": float(early.mean()),
        "early_s": EARLY,
    }


EARLY = 1.0
"""s before the request at which GuideRL's accuracy is also reported."""


def _trajectories(split: str) -> str:
    return "trajectories" if split == "all" else f"{split} trajectories"


def _guide_text(g: dict, split: str = "test") -> str:
    early = ""
    if "accuracy_early" in g:
        early = f", {g['early_s']:g} s before it in {100 * g['accuracy_early']:.1f}%"
    return (
        f"GuideRL: the requesting user named at the request in {100 * g['accuracy']:.1f}% of "
        f"{g['pairs']} ordered pairs of the {_trajectories(split)} (thesis: 99%){early}"
    )


def _meta_text(meta: dict) -> str:
    return (
        f"{meta['trajectories']} {_trajectories(meta.get('split', 'test'))} from `{meta['motion']}` on floor "
        f"`{meta['floor']}`; "
        f"MU pairs offset by {meta['mu_offset']}; seed {meta['seed']}; {meta['date']}."
    )


def main(argv=None) -> int:
    parser = OneLineParser(
        prog="python -m train.evaluate",
        description="Table 5.1 of the thesis: baselines and trained policies through the behaviour engine.",
    )
    parser.add_argument(
        "--su", metavar="RUN", help="a single-user run (or exported policy) to evaluate as SU DRL"
    )
    parser.add_argument("--mu", metavar="RUN", help="a NavRL run (or exported policy) to evaluate as MU DRL")
    parser.add_argument(
        "--guide",
        metavar="RUN",
        help="a GuideRL run (or exported policy): its accuracy on the test pairs, and the goal source of "
        "MU DRL (default: the --mu run's guide_run, else the shipped one)",
    )
    parser.add_argument(
        "--motion",
        default="default",
        help="trajectories: default (its 100 test ones), sample, or a folder of MCAP bags",
    )
    parser.add_argument(
        "--split",
        choices=("test", "train", "all"),
        default="test",
        help="which trajectories of a set of more than 100: the held-out test ones (Table 5.1), the "
        "training ones, or all of them (for a validation set training never saw, made with "
        "`python -m methd_jax.motion synth --seed 1 --n 300 --out DIR`): to choose between checkpoints "
        "without looking at the test set",
    )
    parser.add_argument(
        "--floor", default="lab", help="lab (the lab twin) or a floor JSON in the lab's format"
    )
    parser.add_argument("--trajectories", type=int, help="use only the first N trajectories of the split")
    parser.add_argument(
        "--mu-offset", type=int, default=50, help="user 2's trajectory index offset (default 50)"
    )
    parser.add_argument("--no-su", action="store_true", help="skip the single-user scenario")
    parser.add_argument(
        "--no-mu",
        action="store_true",
        help="skip the multi-user scenario (and GuideRL's accuracy, unless --guide names one)",
    )
    parser.add_argument("--no-heuristic", action="store_true", help="skip the Heuristic baseline")
    parser.add_argument(
        "--no-pretrained",
        action="store_true",
        help="do not evaluate the shipped policies of assets/pretrained where --su / --mu / --guide "
        "name none (baselines only)",
    )
    parser.add_argument(
        "--no-safety", action="store_true", help="skip the policies' 'DRL + safety' rows (safety layer on)"
    )
    parser.add_argument(
        "--procedural",
        type=int,
        metavar="N",
        default=0,
        help="also run the SU policy on N fresh procedural floors with obstacles (generalisation; 0: skip)",
    )
    parser.add_argument("--seed", type=int, default=0, help="key for the LiDAR noise of DRL policies")
    parser.add_argument("--out", type=Path, help="output folder (default runs/eval-<date>-<time>)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    try:
        if args.procedural < 0:
            raise ConfigError(f"--procedural must be >= 0, got {args.procedural}")
        if args.trajectories is not None and args.trajectories < 1:
            raise ConfigError(f"--trajectories must be at least 1, got {args.trajectories}")
        if args.su and args.no_su:
            raise ConfigError("--su and --no-su contradict each other")
        if args.no_su and args.no_mu and not args.guide:
            raise ConfigError(
                "--no-su and --no-mu leave nothing to evaluate (add --guide RUN for GuideRL alone)"
            )
        if args.motion not in ("default", "sample") and not Path(args.motion).is_dir():
            raise ConfigError(f"--motion {args.motion}: not 'default', 'sample' or a folder")
        try:
            floor = floors.lab() if args.floor == "lab" else floors.lab(args.floor)
        except floors.FloorSpecError as err:
            raise ConfigError(str(err)) from None
        bank = load_bank(args.motion, args.split, HipConfig(), require_split=args.split == "train")
        if args.trajectories is not None:
            bank = bank.take(range(min(args.trajectories, bank.num_trajectories)))
        su = {} if args.no_su else {"Static": methods.Static()}
        if not (args.no_heuristic or args.no_su):
            su["Heuristic"] = methods.Heuristic()
        mu = {} if args.no_mu else {"Static": methods.Static()}
        su_run = args.su or (None if args.no_pretrained or args.no_su else shipped("su"))
        if args.procedural and not su_run:  # refused before the long evaluation, not after it
            raise ConfigError("--procedural needs a single-user policy (--su RUN or the shipped one)")
        if su_run:
            su["DRL"] = load_policy(su_run, bank, "su")
            if not args.no_safety:
                su[SAFETY_ROW] = load_policy(su_run, bank, "su", safety=SafetyConfig())
        if args.mu and args.no_mu:
            raise ConfigError("--mu and --no-mu contradict each other")
        mu_run = args.mu or (None if args.no_pretrained or args.no_mu else shipped("nav"))
        guide = args.guide or (_dependencies(args.mu).get("guide") if args.mu else None)
        # GuideRL belongs to the multi-user scenario: --no-mu measures it only when --guide names one
        guide = guide or (None if args.no_pretrained or args.no_mu else shipped("guide"))
        if guide:
            load_guide(guide)  # a bad --guide is refused before the long evaluation
        if mu_run:
            mu["DRL"] = load_policy(mu_run, bank, "nav", guide)
            if not args.no_safety:
                mu[SAFETY_ROW] = load_policy(mu_run, bank, "nav", guide, safety=SafetyConfig())
        if mu and bank.num_trajectories < 2:
            raise ConfigError("the multi-user scenario needs at least 2 trajectories (or pass --no-mu)")
        offset = args.mu_offset % bank.num_trajectories if mu else args.mu_offset
        if mu and offset == 0:
            offset = max(1, bank.num_trajectories // 2)
        out = args.out or Path("runs") / f"eval-{time.strftime('%Y%m%d-%H%M%S')}"
        meta = {
            "motion": args.motion,
            "split": args.split,
            "floor": args.floor,
            "trajectories": bank.num_trajectories,
            "mu_offset": offset,
            "seed": args.seed,
            "su_run": str(su_run) if su_run else None,
            "mu_run": str(mu_run) if mu_run else None,
            "guide_run": str(guide) if guide else None,
            "date": time.strftime("%Y-%m-%d %H:%M"),
        }
        results = evaluate(su, mu, bank, floor, mu_offset=offset, seed=args.seed, progress=not args.quiet)
        if guide:
            meta["guide"] = guide_accuracy(guide, bank)
        if args.procedural:
            meta["procedural"] = procedural(su_run, args.procedural, seed=args.seed + 1)
    except (ConfigError, FileNotFoundError, MotionDataError) as err:
        print(f"python -m train.evaluate: error: {err}", file=sys.stderr)
        return 2
    table, st = write_report(results, out, meta)
    print(_meta_text(meta))
    if table:
        print(table)
    if "procedural" in meta:
        print(_procedural_text(meta["procedural"]))
    if "guide" in meta:
        print(_guide_text(meta["guide"], meta["split"]))
    text = _stats_text(st)
    if text:
        print(text)
    print(f"wrote {out / 'table.md'}, {out / 'results.json'}" + (" and figures" if table else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
