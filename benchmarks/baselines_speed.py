"""
Steps per second of the paper's baselines, SB3's alternatives and SERASAC against stock SB3, interleaved in one
process: on a single-agent task SAC, SERASAC, SUNRISE, ACE and sb3-contrib's TQC and CrossQ against SAC; on a
multi-agent CTDE task (``sb3_sera/...``) MASAC, SERASAC and IET (our adaptation) against MASAC (SB3's SAC with
per-agent actors).

Every model is built with its own defaults on the same task (so each runs at its own default batch size: SAC,
MASAC, SERASAC, SUNRISE, IET, TQC and CrossQ 256, ACE 64, the authors'; CrossQ's critics 1024 wide and its actor
updated every third step, TQC's two critics of 25 quantiles: sb3-contrib's defaults, the settings the ledger runs),
its replay buffer filled with ``--learning-starts`` random transitions, then ``model.train(block)`` (``--mode
train``: gradient steps alone) or ``model.learn(block)`` (``--mode learn``: what a user's ``learn()`` costs an env
step, acting and the env included) is timed in alternating blocks so that machine noise hits all alike. Each figure
is the median over blocks with the interquartile range; the ratio is the reference's median rate over the model's
(its wall-time cost per step, in units of the reference's). ``--batch-size`` times every model at one batch size.

    python benchmarks/baselines_speed.py --env HalfCheetah-v5 --blocks 10 --block-steps 50
    python benchmarks/baselines_speed.py --env sb3_sera/HalfCheetah-6x1-v0 --blocks 10 --block-steps 50
    python benchmarks/baselines_speed.py --algos SAC SERASAC TQC CrossQ --mode learn --threads 1   # one core

The names with a suffix are SERASAC compiled (``compile_update=True``), with DroQ's or CrossQ's critics, and with two
gradient steps an environment step (``UTD2``): the configurations of issue 90's screen, whose other settings (learning
rates, the entropy coefficient's start, ``learning_starts``) change no step's cost; ``-mean`` is compiled SERASAC with
the Ensemble Mean target, the decision's other arm.
"""

import argparse
from collections.abc import Callable
from functools import partial

import torch as th
from sb3_contrib import TQC, CrossQ
from stable_baselines3 import SAC
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from timing import add_interleave_arguments, interleaved_rates, median_iqr

from sb3_sera import ACE, IET, MASAC, SERASAC, SUNRISE
from sb3_sera.common.mujoco_log import route_mujoco_warnings

#: SERASAC's normalized critics (issue 90's screen), compiled as the screen runs them
DROQ = dict(layer_norm=True, dropout_rate=0.01)
CROSSQ = dict(batch_norm=True)
ALGORITHMS: dict[str, Callable[..., OffPolicyAlgorithm]] = {
    "SAC": SAC,
    "MASAC": MASAC,
    "SERASAC": SERASAC,
    "SUNRISE": SUNRISE,
    "ACE": ACE,
    "IET": IET,
    "TQC": TQC,
    "CrossQ": CrossQ,
    "SERASAC-compiled": partial(SERASAC, compile_update=True),
    "SERASAC-compiled-mean": partial(SERASAC, compile_update=True, target_aggregation="mean"),
    "SERASAC-DroQ": partial(SERASAC, compile_update=True, policy_kwargs=DROQ),
    "SERASAC-CrossQ": partial(SERASAC, compile_update=True, policy_kwargs=CROSSQ),
    "SERASAC-DroQ-UTD2": partial(SERASAC, compile_update=True, policy_kwargs=DROQ, gradient_steps=2),
    "SERASAC-CrossQ-UTD2": partial(SERASAC, compile_update=True, policy_kwargs=CROSSQ, gradient_steps=2),
}
#: The algorithms each kind of task runs by default, the reference first
SINGLE_AGENT = ["SAC", "SERASAC", "SUNRISE", "ACE", "TQC", "CrossQ"]
MULTI_AGENT = ["MASAC", "SERASAC", "IET"]


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_interleave_arguments(parser, blocks=10, block_steps=50, warmup_blocks=2)
    parser.add_argument(
        "--algos", nargs="+", choices=list(ALGORITHMS), help=f"default: {SINGLE_AGENT}, or {MULTI_AGENT} on a CTDE task"
    )
    parser.add_argument("--batch-size", type=int, default=None, help="one batch size for all (default: each its own)")
    parser.add_argument("--mode", choices=["train", "learn"], default="train", help="gradient steps, or learn()'s steps")
    parser.add_argument("--threads", type=int, default=th.get_num_threads(), help="torch threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    # The package's multi-agent tasks are its sb3_sera/ ids
    policy = "CTDEPolicy" if args.env.startswith("sb3_sera/") else "MlpPolicy"
    defaults = MULTI_AGENT if policy == "CTDEPolicy" else SINGLE_AGENT
    reference = defaults[0]
    names = [reference, *(name for name in args.algos or defaults if name != reference)]
    models: dict[str, OffPolicyAlgorithm] = {}
    for name in names:
        model = ALGORITHMS[name](policy, args.env, seed=args.seed, learning_starts=args.learning_starts)
        model.learn(args.learning_starts)  # fills the buffer; no gradient step before learning_starts
        models[name] = model
    what = "train() only" if args.mode == "train" else "learn(): env steps, each with its gradient steps"
    print(f"{args.env}, {args.threads} torch thread(s), torch {th.__version__}, {what}")
    width = max(len(name) for name in names)
    print(f"{'algorithm':<{width}} {'batch':>6} {'steps/s (median)':>17} {'IQR':>15}  ratio ({reference} rate / rate)")
    rates = interleaved_rates(models, args.mode, args.blocks, args.block_steps, args.batch_size, args.warmup_blocks)
    stats = {name: median_iqr(values) for name, values in rates.items()}
    for name, (median, low, high) in stats.items():
        batch = args.batch_size or models[name].batch_size
        print(f"{name:<{width}} {batch:>6} {median:>17.1f} {f'{low:.1f}-{high:.1f}':>15}  {stats[reference][0] / median:.2f}x")


if __name__ == "__main__":
    main()
