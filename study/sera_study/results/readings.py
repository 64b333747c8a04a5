"""
The results page's readings, with every number the ledger gives filled in by code: the prose lives in
``results/readings.md`` (beside ``claims.yml``), and each number in it is a placeholder that ``sb3-sera ledger
report`` replaces from the ledger, so that no count, mean, interval or q-value on the page can go stale. Numbers that
are not the ledger's (the paper's, a declared power, a published figure) are written as they are.

A placeholder is ``{{claim: <id> | <field>}}`` (a claim of ``claims.yml``, decided as the page decides it) or
``{{runs: <group> | <task> | <budget> | <field>}}`` (one group of the ledger's published runs; ``<group>`` is its
variant, followed where the variant has several groups on that task and budget by the settings that pick one, as
``sac (learning_starts=10000)``). The fields are :data:`CLAIM_FIELDS` and :data:`RUN_FIELDS`; ``at <step>`` reads
each run's final return from its evaluations up to ``<step>``. An unknown claim, group or field is a ``ValueError``
naming it and what is allowed.
"""

import re
import textwrap
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import yaml

from sera_study.records import FINAL_EVALUATIONS
from sera_study.results import stats
from sera_study.results.claims import ALPHA, ClaimResult
from sera_study.results.claims_text import format_number, interval_text, p_text, rests_on_bh_alone
from sera_study.results.groups import RunGroup
from sera_study.results.measures import signed_bias
from sera_study.results.report.paper import paper_value

#: The readings' template, in the ledger's folder
READINGS_FILE = "readings.md"
#: The filled readings lie between these lines on the results page
BEGIN, END = "<!-- readings:begin -->", "<!-- readings:end -->"
#: A placeholder: ``{{kind: part | part | ...}}``, its parts on one line or across a line break
PLACEHOLDER = re.compile(r"\{\{\s*(\w+):\s*([^{}]*?)\s*\}\}")
#: The width the results page's source keeps to
WIDTH = 120
#: A space that the wrapping does not break at
_KEEP = "\x00"


def _mean_sd(values: np.ndarray) -> str:
    """``mean ± sd`` (sample sd), the sd at the mean's precision."""
    mean = format_number(float(values.mean()))
    decimals = len(mean.partition(".")[2])
    sd = float(values.std(ddof=1)) if len(values) > 1 else 0.0
    return f"{mean} ± {sd:.{decimals}f}"


def _listed(items: Sequence[str]) -> str:
    """``a, b and c``."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def _test_text(result: ClaimResult) -> str:
    """What a claim's test reads: its adjusted p (Holm) or its q-values (BH, BY), and the verdict they give."""
    if result.adjusted_p is None:
        return result.verdict
    if result.claim.primary:
        return f"Holm p {p_text(result.adjusted_p)}: {result.verdict}"
    alone = " on BH alone" if rests_on_bh_alone(result) else ""
    return f"BH q {p_text(result.adjusted_p)}, BY q {p_text(result.by_q)}: {result.verdict}{alone}"


def _tested(result: ClaimResult) -> ClaimResult:
    if result.low is None or result.high is None or result.difference is None:
        raise ValueError(f"claim {result.claim.id} has no interval yet ({result.verdict})")
    return result


#: A claim's fields: what each placeholder ``{{claim: <id> | <field>}}`` gives
CLAIM_FIELDS: dict[str, Callable[[ClaimResult], str]] = {
    "n": lambda r: f"{len(r.arm_values)} vs {len(r.baseline_values)}",
    "arm mean": lambda r: format_number(float(r.arm_values.mean())),
    "baseline mean": lambda r: format_number(float(r.baseline_values.mean())),
    "arm mean sd": lambda r: _mean_sd(r.arm_values),
    "baseline mean sd": lambda r: _mean_sd(r.baseline_values),
    "difference": lambda r: format_number(_tested(r).difference),
    "interval": lambda r: interval_text(_tested(r)),
    "high % of baseline": lambda r: f"{100 * (_tested(r).high or 0.0) / float(r.baseline_values.mean()):.1f}%",
    "welch p": lambda r: p_text(r.welch_p),
    "permutation p": lambda r: p_text(r.permutation_p),
    "adjusted p": lambda r: p_text(r.adjusted_p),
    "by q": lambda r: p_text(r.by_q),
    "verdict": lambda r: r.verdict,
    "test": _test_text,
}


def _spreads(result: ClaimResult) -> tuple[float, float]:
    """The sample standard deviations of a claim's two arms."""
    arm, baseline = result.arm_values, result.baseline_values
    if min(len(arm), len(baseline)) < 2:
        raise ValueError(f"claim {result.claim.id} has fewer than two runs an arm")
    return float(arm.std(ddof=1)), float(baseline.std(ddof=1))


#: A claim's fields with a number: the Welch test's power against a difference of ``<effect>`` at the arms' spreads
#: and sizes, at level 0.05 or ``<alpha>``; the runs an arm that power 0.8 needs there
CLAIM_NUMBER_FIELDS = re.compile(r"(power|runs for 80% power) at ([-\d.,]+)(?: alpha ([\d.]+))?")


def _claim_number_field(result: ClaimResult, match: re.Match[str]) -> str:
    effect, alpha = float(match.group(2).replace(",", "")), float(match.group(3) or ALPHA)
    std, baseline_std = _spreads(result)
    if match.group(1) == "power":
        sizes = len(result.arm_values), len(result.baseline_values)
        return f"{stats.welch_power(effect, std, baseline_std, *sizes, alpha=alpha):.2f}"
    return str(stats.runs_for_power(effect, std, baseline_std, alpha=alpha))


def _finals_at(group: RunGroup, step: int) -> np.ndarray:
    """Each run's final return read at ``step``: the mean of its last evaluations up to it."""
    finals = []
    for run in group.runs:
        returns = [value for at, value in zip(run.timesteps, run.returns, strict=True) if at <= step]
        if not returns:
            raise ValueError(f"{group.label} on {group.env_id}: a run has no evaluation up to step {step}")
        finals.append(float(np.mean(returns[-FINAL_EVALUATIONS:])))
    return np.array(finals)


def _by_seed(group: RunGroup) -> list[Any]:
    return sorted(group.runs, key=lambda run: run.seed)


def _seeds(seeds: Sequence[int]) -> str:
    """``seed 3``, ``seeds 0, 1 and 4``, or ``none``."""
    return "none" if not seeds else f"seed{'s' if len(seeds) > 1 else ''} {_listed([str(seed) for seed in seeds])}"


def _signed(group: RunGroup) -> list[float]:
    """Each run's signed initial-state bias (:func:`~sera_study.results.measures.signed_bias`), where it has one."""
    values = [value for run in group.runs if (value := signed_bias(run)) is not None]
    if not values:
        raise ValueError(f"no run of {group.label} on {group.env_id} has an initial-state bias record")
    return values


def _overestimate(signed: Sequence[float]) -> str:
    """``k of n``: how many of the runs' signed biases are above 0."""
    return f"{sum(value > 0 for value in signed)} of {len(signed)}"


def _wall_times(group: RunGroup) -> str:
    times = [run.wall_time_s for run in group.runs]
    return f"{min(times):,.0f}-{max(times):,.0f} s" if len(times) > 1 else f"{times[0]:,.0f} s"


def _paper_ratio(group: RunGroup, values: np.ndarray) -> str:
    paper = paper_value(group.env_id, group.variant)
    if paper is None:
        raise ValueError(f"the paper reports no value for {group.variant} on {group.env_id}")
    return f"{float(values.mean()) / paper[0]:.2f}"


#: A group's fields: what each placeholder ``{{runs: <group> | <task> | <budget> | <field>}}`` gives
RUN_FIELDS: dict[str, Callable[[RunGroup], str]] = {
    "count": lambda g: str(len(g.runs)),
    "mean": lambda g: format_number(float(g.finals.mean())),
    "mean sd": lambda g: _mean_sd(g.finals),
    "finals": lambda g: _listed([f"{run.final_return:.1f}" for run in _by_seed(g)]),
    "lowest": lambda g: f"{g.finals.min():.1f}",
    "highest": lambda g: f"{g.finals.max():.1f}",
    "seeds": lambda g: _seeds([run.seed for run in _by_seed(g)]),
    "resumed": lambda g: str(sum(bool(run.resumes) for run in g.runs)),
    "resumed seeds": lambda g: _seeds([run.seed for run in _by_seed(g) if run.resumes]),
    "wall times": _wall_times,
    "overestimate": lambda g: _overestimate(_signed(g)),
    "signed bias": lambda g: _mean_sd(np.array(_signed(g))),
    "auc mean": lambda g: format_number(float(g.aucs.mean())),
    "paper ratio": lambda g: _paper_ratio(g, g.finals),
    "auc paper ratio": lambda g: _paper_ratio(g, g.aucs),
}


def _group(spec: str, env_id: str, budget: str, groups: Sequence[RunGroup]) -> RunGroup:
    """The one group of ``groups`` that ``spec`` names on ``env_id`` at ``budget``."""
    variant, _, settings_text = spec.partition("(")
    wanted = yaml.safe_load("{" + settings_text.rstrip(") ").replace("=", ": ") + "}") if settings_text else {}
    here = [g for g in groups if g.env_id == env_id and str(g.n_timesteps) == budget.replace(",", "")]
    found = [g for g in here if g.variant == variant.strip() and all(g.hyperparams.get(k) == v for k, v in wanted.items())]
    if len(found) != 1:
        labels = "; ".join(g.label for g in here) or "none"
        which = "no group" if not found else f"{len(found)} groups"
        raise ValueError(f"{which} of the ledger's runs is '{spec}' on {env_id} at {budget} steps; its groups: {labels}")
    return found[0]


def _value(kind: str, parts: list[str], claims: dict[str, ClaimResult], groups: Sequence[RunGroup]) -> str:
    """What one placeholder gives (see the module's docstring); ``claims`` are the decided claims by id."""
    if kind == "claim" and len(parts) == 2:
        if parts[0] not in claims:
            raise ValueError(f"no claim '{parts[0]}' in the ledger's claims.yml")
        number = CLAIM_NUMBER_FIELDS.fullmatch(parts[1])
        if number:
            return _claim_number_field(claims[parts[0]], number)
        return _field(CLAIM_FIELDS, parts[1], claims[parts[0]])
    if kind == "runs" and len(parts) == 4:
        field, group = parts[3], _group(parts[0], parts[1], parts[2], groups)
        step = re.fullmatch(r"at ([\d,]+)", field)
        if step:
            return _mean_sd(_finals_at(group, int(step.group(1).replace(",", ""))))
        return _field(RUN_FIELDS, field, group)
    raise ValueError(
        "a placeholder is {{claim: <id> | <field>}} or {{runs: <group> | <task> | <budget> | <field>}}, "
        f"not {{{{{kind}: {' | '.join(parts)}}}}}"
    )


def _field(fields: dict[str, Callable[[Any], str]], name: str, item: Any) -> str:
    if name not in fields:
        extra = ", at <step>" if fields is RUN_FIELDS else ", power at <effect> [alpha <a>], runs for 80% power at <effect>"
        raise ValueError(f"no field '{name}': the fields are {', '.join(fields)}{extra}")
    return fields[name](item)


def fill_readings(template: str, decided: Sequence[ClaimResult], groups: Sequence[RunGroup]) -> str:
    """
    ``template`` with each placeholder replaced by what the ledger gives (see the module's docstring).

    :param decided: the ledger's claims, decided (:func:`~sera_study.results.ledger.read_ledger`)
    :param groups: its published runs, grouped
    :raises ValueError: naming the first placeholder the ledger cannot fill, and why
    """

    claims = {result.claim.id: result for result in decided}

    def replace(match: re.Match[str]) -> str:
        parts = [" ".join(part.split()) for part in match.group(2).split("|")]
        try:
            # A number's words stay on one line when the text is wrapped again
            return _value(match.group(1), parts, claims, groups).replace(" ", _KEEP)
        except ValueError as error:
            raise ValueError(f"{READINGS_FILE}: {' '.join(match.group(0).split())}: {error}") from None

    return _rewrapped(PLACEHOLDER.sub(replace, template)).replace(_KEEP, " ")


def _rewrapped(text: str) -> str:
    """``text``'s paragraphs and list items wrapped again at :data:`WIDTH`, now that the numbers are in."""
    items: list[list[str]] = []
    for line in text.strip().splitlines():
        starts = not line.strip() or re.match(r"\s*- ", line) or not items or not items[-1][0].strip()
        items.append([line]) if starts else items[-1].append(line.strip())
    wrapped = []
    for item in items:
        first = item[0]
        bullet = re.match(r"\s*(- )?", first)
        prefix = bullet.group(0) if bullet else ""
        wrapped.append(
            textwrap.fill(
                " ".join([first[len(prefix) :].strip(), *item[1:]]),
                WIDTH,
                initial_indent=prefix,
                subsequent_indent=" " * len(prefix),
                break_long_words=False,
                break_on_hyphens=False,
            )
            if first.strip()
            else ""
        )
    return "\n".join(wrapped)
