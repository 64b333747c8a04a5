"""``python -m sera_study.theory``: the target-estimator study (see the package's docstring)."""

import argparse
from pathlib import Path

import torch as th

from sera_study import theory
from sera_study.theory.estimators import run
from sera_study.theory.report import markdown_tables, plot, write_csv


def main() -> None:
    """Measure every sweep, print the tables and write the files (tables, CSV, figure) under ``--out``."""
    parser = argparse.ArgumentParser(
        prog="python -m sera_study.theory",
        description=theory.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--draws", type=int, default=100_000, help="independent draws per setting")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("docs/results/theory"), help="folder for the figure and tables")
    args = parser.parse_args()

    th.set_num_threads(1)
    rows = run(args.draws, args.seed)
    tables = markdown_tables(rows, args.draws, args.seed)
    print(tables)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "target_estimators.md").write_text(tables)
    write_csv(rows, args.out / "target_estimators.csv")
    plot(rows, args.out / "target_estimators.png")
    print(f"wrote {args.out / 'target_estimators.png'}, .csv and .md")


main()
