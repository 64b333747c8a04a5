"""
A Markdown report from rl-zoo3-style run folders (``<root>/<variant>/<env_name>_<id>/``, as written by
``sb3-sera train``, ``compare`` and ``bench``), read from each run's records (``<env_name>/args.yml`` and
``config.yml``), never from folder names.

Runs are grouped by variant, task, budget and hyperparameters; runs that differ in any of these are never averaged
together: each task and budget has its own section, and a variant run with several settings gets a row per setting,
with a note that says what differs. Per section: a table with the interquartile mean (IQM) of the final evaluation
returns and its 95% stratified-bootstrap confidence interval (``rliable``), the mean ± sample standard deviation
beside the paper's values, the normalized AUC (IQM and interval), the probability that SERASAC improves on each
baseline (with interval), Welch's p-value and SERASAC's improvement in percent; learning curves (IQM and interval
per evaluation); the initial-state value bias over training (paper Fig. 4a); the normalized AUC as bars (Fig. 4b);
the TD-target variance and the critics' value and TD-error correlations over training (Fig. 4c); and the critics'
K x K correlation matrices at one evaluation (Fig. 5). Several sections together add min-max normalized scores
aggregated over tasks and performance profiles.
"""

from sera_study.results.groups import RunGroup, group_runs
from sera_study.results.report.figures import aligned
from sera_study.results.report.load import Skipped, load_runs, run_folders
from sera_study.results.report.paper import PAPER_NAMES, PAPER_RESULTS
from sera_study.results.report.tables import section_table
from sera_study.results.report.write import next_report_folder, report_roots, write_report

__all__ = [
    "PAPER_NAMES",
    "PAPER_RESULTS",
    "RunGroup",
    "Skipped",
    "aligned",
    "group_runs",
    "load_runs",
    "next_report_folder",
    "report_roots",
    "run_folders",
    "section_table",
    "write_report",
]
