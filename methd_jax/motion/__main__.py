"""``python -m methd_jax.motion synth|stats|convert``: make, inspect and convert motion datasets."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from methd_jax.motion import bags, dataset, stats
from methd_jax.motion.synth import synthesize
from methd_jax.motion.trajectory import MotionDataError


def _synth(args) -> int:
    if args.n < 1:
        raise SystemExit("error: --n must be at least 1")
    if args.out is None:
        trajs = dataset.default_dataset(args.n, args.seed, cache=args.cache)
        where = Path(args.cache or dataset.cache_dir()) / "motion"
        print(f"{len(trajs)} trajectories (seed {args.seed}) in the cache under {where}")
        return 0
    trajs = synthesize(args.n, args.seed, progress=dataset.progress_bar("synthesising"))
    files = bags.save(args.out, trajs, progress=dataset.progress_bar("writing MCAP"))
    print(f"wrote {len(files)} trajectories to {args.out}")
    return 0


def _stats(args) -> int:
    if args.path is None:
        trajs = dataset.default_dataset(cache=args.cache)
    else:
        trajs = bags.load(args.path, progress=dataset.progress_bar("reading"))
    st = stats.compute(trajs)
    print(stats.report(st))
    if args.plots:
        for p in stats.plot(st, trajs, args.plots):
            print(f"wrote {p}")
    if args.json:
        plain = {
            k: ({kk: vv for kk, vv in v.items() if kk != "values"} if isinstance(v, dict) else v)
            for k, v in st.items()
        }
        Path(args.json).write_text(json.dumps(plain, indent=2, default=float))
        print(f"wrote {args.json}")
    return 0


def _convert(args) -> int:
    files = bags.convert(args.src, args.dst, progress=dataset.progress_bar("converting"))
    print(f"converted {len(files)} ROS 1 bag(s) to MCAP under {args.dst}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m methd_jax.motion", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser(
        "synth", help="synthesise trajectories (default: the 442-trajectory set into the cache)"
    )
    s.add_argument("--n", type=int, default=dataset.DEFAULT_SIZE, help="number of trajectories (442)")
    s.add_argument("--seed", type=int, default=0, help="generator seed (0)")
    s.add_argument("--out", help="write MCAP files to this directory instead of the cache")
    s.add_argument("--cache", help=f"cache folder (default ${dataset.CACHE_ENV} or ~/.cache/methd-jax)")
    s.set_defaults(run=_synth)
    s = sub.add_parser("stats", help="statistics against the thesis's, and plots")
    s.add_argument(
        "path", nargs="?", help="an .mcap file or a directory of them (default: the synthetic set)"
    )
    s.add_argument("--plots", help="write speed_boxplot.png and trajectories.png to this directory")
    s.add_argument("--json", help="write the figures as JSON to this file")
    s.add_argument("--cache", help="cache folder for the default set")
    s.set_defaults(run=_stats)
    s = sub.add_parser("convert", help="convert ROS 1 .bag recordings (same topics) to MCAP")
    s.add_argument("src", help="a .bag file or a directory of them")
    s.add_argument("dst", help="an output .mcap file (one input) or directory")
    s.set_defaults(run=_convert)
    args = p.parse_args(argv)
    try:
        return args.run(args)
    except (MotionDataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
