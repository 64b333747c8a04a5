"""The ``sb3-sera`` command line (also ``python -m sb3_sera``)."""

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from rl_zoo3.utils import StoreDict

from sb3_sera.experiments import bench, compare, report, zoo


def _compare(args: argparse.Namespace) -> None:
    hyperparams = None
    if args.hyperparams:
        defaults = compare.DEFAULT_HYPERPARAMS if args.env == compare.DEFAULT_ENV else {}
        hyperparams = {algo: {**defaults.get(algo, {}), **args.hyperparams} for algo in args.algos}
    results = compare.run_comparison(
        hyperparams=hyperparams,
        algos=args.algos,
        env_id=args.env,
        seeds=args.seeds,
        n_timesteps=args.n_timesteps,
        out_dir=args.out,
        eval_freq=args.eval_freq,
        n_eval_episodes=args.eval_episodes,
        n_jobs=args.n_jobs,
    )
    table = compare.summary_table(results)
    out = Path(args.out)
    name = compare.env_name(args.env)
    plot = out / f"{name}_learning_curves.png"
    compare.plot_learning_curves(results, plot)
    (out / f"{name}_summary.md").write_text(f"{args.env}, {args.n_timesteps} steps, seeds {list(args.seeds)}\n\n{table}\n")
    print(f"\n{args.env}, {args.n_timesteps} steps, seeds {list(args.seeds)}\n{table}")
    print(f"\nLearning curves: {plot}\nRun folders: {out}/<algo>/{name}_<seed>/")


def _bench(args: argparse.Namespace) -> None:
    by_task = bench.run_grid(args.grid, args.out, n_jobs=args.n_jobs, ray_address=args.ray_address)
    for task, results in by_task.items():
        print(f"\n{task}\n{compare.summary_table(results)}")
    print(f"\nRun folders and summaries: {args.out}")


def _report(args: argparse.Namespace) -> None:
    path = report.write_report(args.roots, args.out, tensorboard_dirs=args.tensorboard_log or ())
    print(path.read_text())
    print(f"\nReport: {path}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sb3-sera", description="SERA for Stable-Baselines3")
    from sb3_sera import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    comp = commands.add_parser(
        "compare",
        help="train algorithms on one task for several seeds, print a table and plot learning curves",
        description="Train algorithms on one task for several seeds, print a table and plot learning curves.",
    )
    comp.add_argument("--algos", nargs="+", default=list(compare.DEFAULT_ALGOS), help="algorithm names")
    comp.add_argument("--env", default=compare.DEFAULT_ENV, help="Gymnasium id")
    comp.add_argument("--seeds", nargs="+", type=int, default=list(compare.DEFAULT_SEEDS))
    comp.add_argument("-n", "--n-timesteps", type=int, default=compare.DEFAULT_TIMESTEPS)
    comp.add_argument("--eval-freq", type=int, default=1000, help="environment steps between evaluations")
    comp.add_argument("--eval-episodes", type=int, default=5)
    comp.add_argument("--n-jobs", type=int, default=None, help="runs at a time (default: one per core)")
    comp.add_argument(
        "--out", default="logs/compare", help="root of the run folders (a finished run found there is not run again)"
    )
    comp.add_argument(
        "-params",
        "--hyperparams",
        nargs="+",
        action=StoreDict,
        default=None,
        help="hyperparameters for every algorithm, as rl-zoo3's -params: learning_starts:10000 batch_size:256",
    )
    comp.set_defaults(func=_compare)
    grid = commands.add_parser(
        "bench",
        help="run a grid of variants x tasks x seeds from a YAML file, locally or on Ray; resumes where it stopped",
        description=bench.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    grid.add_argument("grid", help="the grid's YAML file")
    grid.add_argument("--out", default="logs/bench", help="root of the run folders")
    grid.add_argument("--n-jobs", type=int, default=None, help="local runs at a time (default: one per core)")
    grid.add_argument("--ray-address", default=None, help="run on this Ray cluster ('auto': the one started here)")
    grid.set_defaults(func=_bench)
    rep = commands.add_parser(
        "report",
        help="a Markdown report (paper tables, Welch tests, AUC, figures) from rl-zoo3-style run folders",
        description=report.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rep.add_argument("roots", nargs="+", help="folders holding <algo>/<env>_<id>/evaluations.npz")
    rep.add_argument("--tensorboard-log", nargs="+", default=None, help="TensorBoard folders of the same runs")
    rep.add_argument("--out", default="logs/report", help="folder for report.md and its figures")
    rep.set_defaults(func=_report)
    for command in zoo.ZOO_COMMANDS:
        # Listed for --help; main() hands their arguments to rl-zoo3 untouched
        commands.add_parser(command, add_help=False, help=f"rl-zoo3's {command} with sb3-sera's algorithms (zoo flags)")
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``sb3-sera``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in zoo.ZOO_COMMANDS:
        # rl-zoo3 parses these arguments itself: every zoo flag keeps working
        zoo.run_zoo(argv[0], argv[1:])
        return
    args = build_parser().parse_args(argv)
    args.func(args)
