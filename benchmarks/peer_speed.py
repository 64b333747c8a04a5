"""
``learn()`` steps per second of SERASAC against its peers, interleaved in one process on one core: SB3 SAC, SERASAC
eager and with ``compile_update=True``, and, when SBX (the JAX port of SB3, ``pip install sbx-rl``) is installed,
SBX's SAC with its two critics, SBX's SAC with five critics of [256, 256] (SERASAC's ensemble size) and SBX's CrossQ.
SBX is a benchmark-only extra (``pip install -e ".[peers]"``), never a dependency of the package or its tests: without
it the table has the SB3 rows alone.

Every model is built with its defaults on the same task, learns ``--learning-starts`` random steps and a few gradient
steps (compilation and JAX's tracing happen here), then all take turns learning ``--block-steps`` steps, one gradient
step per environment step, in alternating order so that machine noise hits them alike. Each figure is the median
over ``--blocks`` blocks; the cost is SB3 SAC's median rate over the model's. Run it on one core with one thread, so
that torch, JAX and MuJoCo do not compete for cores:

    OMP_NUM_THREADS=1 taskset -c 0 python benchmarks/peer_speed.py --env HalfCheetah-v5 --blocks 3 --block-steps 1000
"""

import argparse
import importlib.util
import os
from collections.abc import Callable
from typing import Any

import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from timing import add_interleave_arguments, interleaved_rates, median_iqr

from sb3_sera import SERASAC
from sb3_sera.common.mujoco_log import route_mujoco_warnings

Builder = Callable[[str, dict[str, Any]], BaseAlgorithm]


def builders() -> dict[str, Builder]:
    """Each model's constructor (task id, common keywords): SB3's and ours always, SBX's where it is installed."""
    table: dict[str, Builder] = {
        "SB3 SAC": lambda env, kw: SAC("MlpPolicy", env, **kw),
        "SERASAC eager": lambda env, kw: SERASAC("MlpPolicy", env, **kw),
        "SERASAC compile_update=True": lambda env, kw: SERASAC("MlpPolicy", env, compile_update=True, **kw),
    }
    if importlib.util.find_spec("sbx") is not None:
        import sbx

        table.update(
            {
                "SBX SAC, 2 critics": lambda env, kw: sbx.SAC("MlpPolicy", env, **kw),
                "SBX SAC, 5 critics of [256, 256]": lambda env, kw: sbx.SAC(
                    "MlpPolicy", env, policy_kwargs=dict(n_critics=5, net_arch=[256, 256]), **kw
                ),
                "SBX CrossQ": lambda env, kw: sbx.CrossQ("MlpPolicy", env, **kw),
            }
        )
    return table


def main() -> None:
    route_mujoco_warnings()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_interleave_arguments(parser, blocks=3, block_steps=1000, warmup_blocks=1, unit="learn() steps")
    parser.add_argument("--models", nargs="+", help="a subset of the models, by their names in the table")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)
    # One thread for JAX's CPU backend too, as for torch (read when JAX is imported, in builders())
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    available = builders()
    names = args.models or list(available)
    unknown = sorted(set(names) - set(available))
    if unknown:
        raise SystemExit(f"unknown or unavailable models {unknown}: choose among {list(available)} (SBX's need sbx-rl)")
    common = dict(seed=args.seed, learning_starts=args.learning_starts, verbose=0)
    models = {}
    for name in names:
        model = available[name](args.env, common)
        model.learn(args.learning_starts + 10)
        models[name] = model
    rates = interleaved_rates(models, "learn", args.blocks, args.block_steps, None, args.warmup_blocks)
    stats = {name: median_iqr(values) for name, values in rates.items()}
    load = ", ".join(f"{value:.2f}" for value in os.getloadavg())
    print(f"{args.env}, learn() after {args.learning_starts} steps, {args.blocks} blocks of {args.block_steps} steps")
    print(f"one thread, torch {th.__version__}; load average {load} (1, 5, 15 min)")
    reference = stats["SB3 SAC"][0] if "SB3 SAC" in stats else None
    print("| model | steps/s (median) | IQR | cost x SB3 SAC |\n|---|---|---|---|")
    for name, (median, low, high) in stats.items():
        cost = f"{reference / median:.2f}" if reference else "-"
        print(f"| {name} | {median:.1f} | {low:.1f}-{high:.1f} | {cost} |")


if __name__ == "__main__":
    main()
