"""
The target-estimator study's output (:mod:`sera_study.theory`): Markdown tables, a CSV file and the figure,
which ``python -m sera_study.theory`` writes.
"""

import csv
from collections.abc import Sequence
from pathlib import Path

from sera_study.results.report.figures import pyplot
from sera_study.theory.estimators import (
    DEFAULT_ALPHA,
    DEFAULT_TEMPERATURE,
    ESTIMATOR_NAMES,
    REFERENCE_NAMES,
    SWEEP_AXIS,
    Row,
)


def markdown_tables(rows: Sequence[Row], n_draws: int, seed: int) -> str:
    """
    The measurements as Markdown: per sweep a variance table (with the references) and a bias table, then the
    diagnostics of Lemma 4.1 and Propositions 4.2-4.3.

    :param rows: the measurements
    :param n_draws: draws per setting (for the header)
    :param seed: random seed (for the header)
    """
    lines = [
        f"Synthetic ensembles, Q* = 0, {n_draws} draws per setting, seed {seed}; SERA: alpha {DEFAULT_ALPHA}, "
        f"tau {DEFAULT_TEMPERATURE}; sigmas geometric with geometric mean 1; spread = sigma_max / sigma_min.",
        "",
    ]
    names = ", ".join(ESTIMATOR_NAMES)
    for sweep, axis in SWEEP_AXIS.items():
        sweep_rows = [row for row in rows if row.setting.sweep == sweep]
        if not sweep_rows:
            continue
        first = sweep_rows[0].setting
        fixed = {
            "spread": f"K = {first.n_critics}, rho = 0",
            "K-equal": "all sigmas = 1, rho = 0",
            "K-hetero": f"spread = {first.spread:g}, rho = 0",
            "correlation": f"K = {first.n_critics}, spread = {first.spread:g}",
            "scale": f"K = {first.n_critics}, spread = {first.spread:g}, rho = 0; scale = geometric mean of the sigmas, "
            "against tau = 1; bias in units of scale, variance in units of scale^2",
        }[sweep]
        lines += [f"### Sweep `{sweep}` ({fixed})", "", f"Variance of the target ({names}; then references):", ""]
        header = [axis, *ESTIMATOR_NAMES, *REFERENCE_NAMES]
        lines += ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
        for row in sweep_rows:
            cells = [f"{row.variance(name):.4g}" for name in ESTIMATOR_NAMES]
            cells += [f"{row.reference(name):.4g}" for name in REFERENCE_NAMES]
            lines.append(f"| {row.axis_value:g} | " + " | ".join(cells) + " |")
        lines += ["", "Bias of the target (mean over draws minus Q*; +- one standard error):", ""]
        header = [axis, *ESTIMATOR_NAMES]
        lines += ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
        for row in sweep_rows:
            cells = [f"{row.bias(name):+.4f} +- {row.bias_se(name):.4f}" for name in ESTIMATOR_NAMES]
            lines.append(f"| {row.axis_value:g} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "### SERA diagnostics (default SERA: median excluded, absolute tau)",
        "",
        "Lemma 4.1 pairs: non-median pairs with d_i < d_j, and among them w_i < w_j (violations) or w_i == w_j "
        "(float ties); Prop. 4.2: draws with the target outside [min, max]; Prop. 4.3: variance by the proof's formula "
        "(weights held fixed) against the measured variance (both in units of scale^2).",
        "",
        "| sweep | setting | ordered pairs | violations | ties | outside [min, max] | formula Var | measured Var |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        diag = row.diagnostics
        axis = SWEEP_AXIS[row.setting.sweep]
        lines.append(
            f"| {row.setting.sweep} | {axis} = {row.axis_value:g} | {diag.ordered_pairs} | "
            f"{diag.ordering_violations} | {diag.ordering_ties} | {diag.bound_violations} | "
            f"{diag.formula_variance / row.setting.scale**2:.4g} | {diag.measured_variance / row.setting.scale**2:.4g} |"
        )
    lines += [
        "",
        "Lemma 4.1 at the batch level: each critic's share of the target (K = 5, rho = 0), by spread. "
        "P(median): how often it is the anchor; w: average softmax weight (0 when it is the anchor); "
        "w~: average effective weight (alpha when anchor, else (1 - alpha) w).",
        "",
        "| spread | critic | sigma | P(median) | mean w | mean w~ |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        if row.setting.sweep != "spread":
            continue
        diag = row.diagnostics
        for i, sigma in enumerate(row.setting.sigmas.tolist()):
            lines.append(
                f"| {row.setting.spread:g} | {i} | {sigma:.3g} | {diag.median_frequency[i].item():.3f} | "
                f"{diag.mean_weight[i].item():.3f} | {diag.mean_effective_weight[i].item():.3f} |"
            )
    return "\n".join(lines) + "\n"


def write_csv(rows: Sequence[Row], path: Path) -> None:
    """
    One line per setting and estimator (references as extra columns).

    :param rows: the measurements
    :param path: the CSV file to write
    """
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(
            [
                "sweep",
                "n_critics",
                "spread",
                "correlation",
                "scale",
                "estimator",
                "bias",
                "bias_se",
                "variance",
                "variance_se",
                "mse",
                *(name.replace(" ", "_") + "_variance" for name in REFERENCE_NAMES),
            ]
        )
        for row in rows:
            setting = row.setting
            for name, moment in row.moments.items():
                writer.writerow(
                    [
                        setting.sweep,
                        setting.n_critics,
                        setting.spread,
                        setting.correlation,
                        setting.scale,
                        name,
                        f"{moment.bias:.6g}",
                        f"{moment.bias_se:.3g}",
                        f"{moment.variance:.6g}",
                        f"{moment.variance_se:.3g}",
                        f"{moment.mse:.6g}",
                        *(f"{row.references[ref]:.6g}" for ref in REFERENCE_NAMES),
                    ]
                )


STYLES: dict[str, dict[str, str]] = {
    "mean": {"color": "tab:blue", "marker": "o"},
    "min": {"color": "tab:red", "marker": "v"},
    "median": {"color": "tab:green", "marker": "s"},
    "SERA": {"color": "tab:purple", "marker": "D"},
    "SERA-Median": {"color": "tab:orange", "marker": "^"},
    "SERA-relative": {"color": "tab:brown", "marker": "x"},
}
REFERENCE_STYLES: dict[str, dict[str, str]] = {
    "best critic": {"color": "0.45", "linestyle": "--"},
    "average critic": {"color": "0.45", "linestyle": ":"},
    "oracle BLUE": {"color": "black", "linestyle": "-."},
}
PANEL_TITLES: dict[str, str] = {
    "spread": "K = 5, noise spread grows",
    "K-equal": "equal sigmas (Prop. 4.3 setting), K grows",
    "K-hetero": "spread 10, K grows",
    "correlation": "K = 5, spread 10, correlation grows",
    "scale": "K = 5, spread 10, noise scale vs tau = 1",
}
AXIS_TITLES: dict[str, str] = {
    "spread": "noise spread sigma_max / sigma_min (log)",
    "K": "number of critics K",
    "rho": "pairwise error correlation rho",
    "scale": "noise scale (geometric mean sigma, log)",
}


#: Limits of the zoomed row of the figure (variance relative to the median target)
ZOOM_LIMITS = (0.55, 1.75)


def plot(rows: Sequence[Row], path: Path) -> None:
    """
    Against each sweep's quantity (one column per sweep): bias (top row), variance (middle row, log scale, with the
    reference variances) and, zoomed, each estimator's variance over the median target's (bottom row).

    :param rows: the measurements
    :param path: the PNG file to write
    """
    sweeps = [sweep for sweep in SWEEP_AXIS if any(row.setting.sweep == sweep for row in rows)]
    plt = pyplot()
    fig, axes = plt.subplots(3, len(sweeps), figsize=(4.2 * len(sweeps), 10.5), squeeze=False)
    for column, sweep in enumerate(sweeps):
        sweep_rows = [row for row in rows if row.setting.sweep == sweep]
        x = [row.axis_value for row in sweep_rows]
        bias_ax, var_ax, zoom_ax = axes[:, column]
        for name in ESTIMATOR_NAMES:
            style = STYLES[name]
            bias_ax.plot(x, [row.bias(name) for row in sweep_rows], label=name, markersize=4, **style)
            var_ax.plot(x, [row.variance(name) for row in sweep_rows], markersize=4, **style)
            ratio = [row.variance(name) / row.variance("median") for row in sweep_rows]
            zoom_ax.plot(x, ratio, markersize=4, **style)
        for ref, style in REFERENCE_STYLES.items():
            var_ax.plot(x, [row.reference(ref) for row in sweep_rows], label=ref, linewidth=1.2, **style)
        bias_ax.axhline(0.0, color="0.7", linewidth=0.8, zorder=0)
        bias_ax.set_title(PANEL_TITLES[sweep], fontsize=10)
        scaled = sweep == "scale"
        bias_ax.set_ylabel("bias  (E[target] - Q*) / scale" if scaled else "bias  E[target] - Q*")
        var_ax.set_ylabel("Var[target] / scale^2 (log)" if scaled else "variance  Var[target] (log)")
        var_ax.set_yscale("log")
        zoom_ax.set_ylabel("Var[target] / Var[median] (zoom)")
        zoom_ax.set_ylim(*ZOOM_LIMITS)
        axis = SWEEP_AXIS[sweep]
        for ax in (bias_ax, var_ax, zoom_ax):
            ax.set_xlabel(AXIS_TITLES[axis])
            ax.grid(True, which="major", alpha=0.3)
            if axis in ("spread", "scale"):
                ax.set_xscale("log")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    ref_handles, ref_labels = axes[1, 0].get_legend_handles_labels()
    fig.legend(handles + ref_handles, labels + ref_labels, loc="lower center", ncol=9, fontsize=10, frameon=False)
    fig.suptitle(
        f"TD-target estimators on synthetic ensembles (Q* = 0, Gaussian noise, sigmas geometric; SERA alpha "
        f"{DEFAULT_ALPHA}, tau {DEFAULT_TEMPERATURE}). Bottom row: lines outside the window are off-scale.",
        fontsize=11,
    )
    fig.tight_layout(rect=(0.0, 0.035, 1.0, 0.975))
    fig.savefig(path, dpi=100)
    plt.close(fig)
