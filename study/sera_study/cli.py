"""
The ``sb3-sera`` command line (also ``python -m sera_study``). Its parser imports nothing heavy: ``--help`` and an
argument's error are answered before torch and Stable-Baselines3 are imported, which the chosen command then does.
"""

import argparse
import ast
import contextlib
import importlib.util
import itertools
import os
import re
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from sera_study import defaults

if TYPE_CHECKING:
    from sera_study.records import RunResult


def _print_report(results: "list[RunResult]", out: str, name: str, reps: int, summary: str = "") -> None:
    """
    Report the runs just made in a new ``<out>/reports/<name>_<n>/``; print its headline (each task's returns table,
    where there is no ``summary``) and where the report, its figures and the runs are, then ``summary`` (the
    comparison in short and what it means), last, where the eye lands.
    """
    from sera_study.results import report

    folder = report.next_report_folder(Path(out) / "reports", name)
    path = report.write_report(results, folder, reps=reps, sources=[out], log=lambda line: print(line, file=sys.stderr))
    tables = "" if summary else f"\n{_headline(path.read_text())}"
    print(f"{tables}\nReport: {path}{_figures(path)}\nRun folders: {out}/<variant>/<env_name>_<id>/")
    if summary:
        print(f"\n{summary}")


def _headline(report_text: str) -> str:
    """
    What a terminal shows of a report: each task's heading and its first table (the returns); the claims, figures and
    notes stay in the file, whose path follows.
    """
    lines = []
    for section in report_text.split("\n## ")[1:]:
        heading, *body = section.splitlines()
        start = next((index for index, line in enumerate(body) if line.startswith("|")), len(body))
        table = list(itertools.takewhile(lambda line: line.startswith("|"), body[start:]))
        if table:
            lines += [f"## {heading}", "", *table, ""]
    return "\n".join(lines)


def _figures(report_path: Path) -> str:
    """The report's figures, a line each, to follow its path."""
    return "\nFigures:" + "".join(f"\n  {figure}" for figure in sorted(report_path.parent.glob("*.png")))


def _compare(args: argparse.Namespace) -> None:
    from sera_study.records import env_name
    from sera_study.results import summary as summaries
    from sera_study.runs import compare

    common, per_algo = compare.parse_params(args.hyperparams or [], args.algos)
    results = compare.run_comparison(
        algos=args.algos,
        env_id=args.env,
        seeds=args.seeds,
        n_timesteps=args.n_timesteps,
        out_dir=args.out,
        params=common,
        algo_params=per_algo,
        eval_freq=args.eval_freq,
        n_eval_episodes=args.eval_episodes,
        n_jobs=args.n_jobs,
        num_threads=args.num_threads,
        device=args.device,
        studies=args.studies,
        checkpoint_freq=args.checkpoint_freq,
        keep_checkpoints=args.keep_checkpoints,
        accept_older=args.accept_older,
    )
    summary = f"{summaries.summary(results, args.algos)}\n{summaries.reading(results, args.algos)}"
    _print_report(results, out=args.out, name=env_name(args.env), reps=args.reps, summary=summary)


def _bench(args: argparse.Namespace) -> None:
    from sera_study.runs import bench
    from sera_study.runs.backends import default_threads

    # Runs that share GPUs: as many at a time as the GPUs hold (execute counts them), each with one torch thread
    shared = args.gpus_per_run is not None
    n_jobs = args.n_jobs or (None if shared else os.cpu_count() or 1)
    threads = args.num_threads or (1 if args.ray_address or shared else default_threads(n_jobs or 1))
    results = bench.run_grid(
        args.grid,
        args.out,
        n_jobs=n_jobs,
        ray_address=args.ray_address,
        num_threads=threads,
        device=args.device,
        checkpoint_freq=args.checkpoint_freq,
        keep_checkpoints=args.keep_checkpoints,
        accept_older=args.accept_older,
        gpus_per_run=args.gpus_per_run,
    )
    _print_report(results, out=args.out, name=Path(args.grid).stem, reps=args.reps)


def _report(args: argparse.Namespace) -> None:
    from sera_study.results import report

    path = report.report_roots(
        args.roots,
        args.out,
        overwrite=args.overwrite,
        reps=args.reps,
        matrix_step=args.matrix_step,
        log=lambda line: print(line, file=sys.stderr),
    )
    print(_headline(path.read_text()))
    print(f"Report, with every claim, figure and note: {path}{_figures(path)}")


def _ledger_add(args: argparse.Namespace) -> None:
    from sera_study.results import intake

    outcome = intake.add_runs(args.sources, args.ledger, unclaimed=args.unclaimed, below_budget=args.below_budget)
    for folder in outcome.added:
        enters = outcome.enters.get(folder) or []
        print(f"added {folder}" + (f": enters {', '.join(enters)}" if enters else ": enters no declared claim"))
    for skipped in outcome.refused:
        print(f"refused {skipped.folder}: {skipped.reason}")
    print(f"{len(outcome.added)} run(s) added to {args.ledger}, {len(outcome.refused)} refused")
    if outcome.added:
        print(
            f"`sb3-sera ledger report` now rewrites {defaults.DOCS_DIR}/ (the report, its figures, the results page) "
            "from the ledger"
        )


def _ledger_report(args: argparse.Namespace) -> None:
    from sera_study.results import ledger

    path = ledger.write_results(args.ledger, args.docs, reps=args.reps)
    print(f"Report: {path}{_figures(path)}\nResults block rewritten in {path.parent / ledger.RESULTS_PAGE}")


def _add_run_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--num-threads",
        type=int,
        default=None,
        help="torch threads per run (default: the cores divided among the runs at a time, at least 1)",
    )
    parser.add_argument("--device", default="auto", help="torch device of every run: auto, cpu, cuda, cuda:1, ...")
    parser.add_argument("--reps", type=int, default=defaults.REPS, help="bootstrap resamples of the report's intervals")
    parser.add_argument(
        "--checkpoint-freq",
        type=int,
        default=None,
        help="steps between a run's checkpoints, from which the same command resumes an interrupted run (0: none; "
        f"default: {defaults.CHECKPOINT_FREQ:,}, or a third of the budget where that is less)",
    )
    parser.add_argument("--keep-checkpoints", action="store_true", help="keep a finished run's last checkpoint")
    parser.add_argument(
        "--accept-older",
        metavar="REASON",
        default=None,
        help="read back finished runs made by other code than now's (whose numbers it may change) instead of training "
        "them again, recording REASON, the difference and both codes in each run's accepted.json (default: never)",
    )


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The description as written, and every option's default after its help (unless the help names it)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        return text if "default:" in text else super()._get_help_string(action) or ""


def _exit(code: int, message: str) -> None:
    """Exit with ``code`` after saying ``message`` on standard error, if it is still open (a pipe's reader may
    have ended with the same Ctrl-C): the exit never waits on an output that is gone."""
    with contextlib.suppress(OSError, ValueError):
        print(message, file=sys.stderr, flush=True)
    sys.exit(code)


def module_doc(name: str) -> str | None:
    """The docstring of ``sera_study.<name>``, read from its source without importing it (or torch)."""
    spec = importlib.util.find_spec(f"sera_study.{name}")
    assert spec is not None and spec.origin is not None
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text(encoding="utf-8")))


def plain_text(doc: str | None) -> str:
    """A module's docstring for the terminal: Sphinx roles and double backquotes as plain text."""
    text = re.sub(r":\w+:`~?(?:[\w.]*\.)?([\w]+)`", r"\1", doc or "")
    return text.replace("``", "")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sb3-sera", description="SERA for Stable-Baselines3")
    # The library's version from its metadata: importing it would import torch before --help is answered
    parser.add_argument("--version", action="version", version=f"%(prog)s {metadata.version('sb3-sera')}")
    commands = parser.add_subparsers(dest="command", required=True)
    for add_command in (_add_compare, _add_bench, _add_report, _add_ledger):
        add_command(commands)
    for command in defaults.ZOO_COMMANDS:
        # Listed for --help; main() hands their arguments to rl-zoo3 untouched
        commands.add_parser(command, add_help=False, help=f"rl-zoo3's {command} with sb3-sera's algorithms (zoo flags)")
    return parser


def _add_compare(commands: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """``sb3-sera compare``'s arguments."""
    comp = commands.add_parser(
        "compare",
        help="train algorithms on one task for several seeds with hyperparams/<algo>.yml, then report them",
        description=plain_text(module_doc("runs.compare")),
        formatter_class=HelpFormatter,
    )
    comp.add_argument("--algos", nargs="+", default=list(defaults.DEFAULT_ALGOS), help="algorithm names")
    comp.add_argument("--env", default=defaults.DEFAULT_ENV, help="Gymnasium id")
    comp.add_argument("--seeds", nargs="+", type=int, default=list(defaults.DEFAULT_SEEDS), help="seeds of every algorithm")
    comp.add_argument("-n", "--n-timesteps", type=int, default=defaults.DEFAULT_TIMESTEPS, help="environment steps of a run")
    comp.add_argument("--eval-freq", type=int, default=1000, help="environment steps between evaluations")
    comp.add_argument("--eval-episodes", type=int, default=5, help="episodes of each evaluation")
    comp.add_argument("--n-jobs", type=int, default=None, help="runs at a time (default: one per core)")
    comp.add_argument(
        "--out", default="logs/compare", help="root of the run folders (a finished run found there is not run again)"
    )
    comp.add_argument(
        "-params",
        "--hyperparams",
        nargs="+",
        default=None,
        help="overrides of hyperparams/<algo>.yml: key:value for every algorithm (learning_starts:1000), "
        "algo:key:value for one (serasac:sera_alpha:0.3); all checked before the first run (default: none)",
    )
    comp.add_argument(
        "--studies",
        nargs="+",
        default=[],
        help="shared settings the algorithms may differ in (learning_starts, batch_size, ...); every other shared "
        "setting must be the same for all, or the comparison is refused naming it",
    )
    _add_run_flags(comp)
    comp.set_defaults(func=_compare)


def _add_bench(commands: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """``sb3-sera bench``'s arguments."""
    grid = commands.add_parser(
        "bench",
        help="run a grid of variants x tasks x seeds from a YAML file, locally or on Ray; resumes where it stopped",
        description=plain_text(module_doc("runs.bench")),
        formatter_class=HelpFormatter,
    )
    grid.add_argument("grid", help="the grid's YAML file")
    grid.add_argument("--out", default="logs/bench", help="root of the run folders")
    grid.add_argument("--n-jobs", type=int, default=None, help="local runs at a time (default: one per core)")
    grid.add_argument(
        "--ray-address", default=None, help="run on this Ray cluster ('auto': the one started here; default: local processes)"
    )
    grid.add_argument(
        "--gpus-per-run",
        type=float,
        default=None,
        metavar="SHARE",
        help="each run's share of a GPU, on Ray or here (0.125: eight runs a card; 2: two GPUs a run); the run uses the "
        "GPU it is given, and here --n-jobs defaults to the runs the GPUs hold (default: no GPU shared)",
    )
    _add_run_flags(grid)
    grid.set_defaults(func=_bench)


def _add_report(commands: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """``sb3-sera report``'s arguments."""
    rep = commands.add_parser(
        "report",
        help="a Markdown report (IQM and bootstrap intervals, paper tables, figures) from rl-zoo3-style run folders",
        description=plain_text(module_doc("results.report")),
        formatter_class=HelpFormatter,
    )
    rep.add_argument("roots", nargs="+", help="folders holding <variant>/<env_name>_<id>/ run folders")
    rep.add_argument("--out", default="logs/report", help="folder for report.md and its figures")
    rep.add_argument("--overwrite", action="store_true", help="replace a report already in --out")
    rep.add_argument("--reps", type=int, default=defaults.REPS, help="bootstrap resamples of every interval")
    rep.add_argument(
        "--matrix-step", type=int, default=None, help="step of the correlation matrices (default: the last evaluation)"
    )
    rep.set_defaults(func=_report)


def _add_ledger(commands: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """``sb3-sera ledger add`` and ``ledger report``'s arguments."""
    led = commands.add_parser(
        "ledger",
        help="the committed results ledger (results/): add finished runs, regenerate the README's results from it",
        description=plain_text(module_doc("results.ledger")),
        formatter_class=HelpFormatter,
    )
    led_commands = led.add_subparsers(dest="ledger_command", required=True)
    led_add = led_commands.add_parser("add", help="copy finished runs' records from bench/compare outputs into the ledger")
    led_add.add_argument("sources", nargs="+", help="folders holding <variant>/<env_name>_<id>/ run folders")
    led_add.add_argument("--ledger", default=defaults.LEDGER_DIR, help="the ledger's folder")
    led_add.add_argument(
        "--unclaimed",
        action="store_true",
        help="also add runs that enter no claim the ledger declares (by default refused, naming why)",
    )
    led_add.add_argument(
        "--below-budget",
        action="store_true",
        help="with --unclaimed, also add runs shorter than every claim's budget (a demo's: by default refused)",
    )
    led_add.set_defaults(func=_ledger_add)
    led_report = led_commands.add_parser(
        "report", help="regenerate docs/results/ (report, figures, results page) from the ledger"
    )
    led_report.add_argument("--ledger", default=defaults.LEDGER_DIR, help="the ledger's folder")
    led_report.add_argument("--docs", default=defaults.DOCS_DIR, help="folder of the full report and its figures")
    led_report.add_argument("--reps", type=int, default=defaults.LEDGER_REPS, help="bootstrap resamples of every interval")
    led_report.set_defaults(func=_ledger_report)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``sb3-sera``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in defaults.ZOO_COMMANDS:
        from sb3_sera.common.arguments import UnknownKeywordError
        from sera_study.runs import zoo

        # rl-zoo3 parses these arguments itself: every zoo flag keeps working
        try:
            zoo.run_zoo(argv[0], argv[1:])
        except (ValueError, UnknownKeywordError) as error:
            sys.exit(f"sb3-sera {argv[0]}: error: {' '.join(str(error).split())}")
        return
    parser = build_parser()
    args = parser.parse_args(argv)
    # Parsed: now the command's modules (torch, Stable-Baselines3)
    import yaml

    from sb3_sera.common.arguments import UnknownKeywordError
    from sera_study.runs.backends import Interrupted

    try:
        args.func(args)
    except KeyboardInterrupt:
        _exit(130, f"sb3-sera {args.command}: interrupted")
    except Interrupted as error:
        _exit(130, f"sb3-sera {args.command}: {error}")
    except (ValueError, UnknownKeywordError, RuntimeError, FileNotFoundError, yaml.YAMLError) as error:
        # A user's mistake or a failed run: one line, no traceback
        message = " ".join(str(error).split())
        parser.exit(2 if isinstance(error, ValueError) else 1, f"sb3-sera {args.command}: error: {message}\n")
