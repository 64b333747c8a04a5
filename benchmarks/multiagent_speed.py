"""
``learn()`` steps per second of the multi-agent models against single-agent SERASAC, interleaved in one process.

Each model is built with its defaults (SB3's and SERASAC's; the multi-agent ones with ``"CTDEPolicy"`` on
``--ma-env``), its replay buffer filled with ``--learning-starts`` random transitions and a few gradient steps
taken (a compiled step compiles there, and the script prints how long that took), then all are timed in
alternating blocks of ``learn()`` (one environment step and one gradient step per step), so that machine noise hits
them alike. The models:

- ``SERASAC``: single-agent SERASAC on ``--env`` (the reference every ratio is taken against);
- ``SERASAC-MA``: SERASAC on the multi-agent task, the agents' actors stacked into one network (the default);
- ``SERASAC-MA-loop``: the same with one SB3 actor per agent run in a loop (the layout before the stacked network);
- ``MASAC`` and ``MASAC-loop``: SB3's SAC with the CTDE policy, stacked and looped;
- with ``--compile``, ``SERASAC+compile``, ``SERASAC-MA+compile`` and ``MASAC+compile``: the same with
  ``compile_update=True`` (or ``"reduce-overhead"``, CUDA graphs, with ``--cuda-graphs``).

Each figure is the median over blocks with its interquartile range, and its rate over single-agent SERASAC's (eager
for the eager models, compiled for the compiled ones).

    OMP_NUM_THREADS=1 python benchmarks/multiagent_speed.py --threads 1 --blocks 10 --block-steps 100
    python benchmarks/multiagent_speed.py --device cuda --compile --cuda-graphs
"""

import argparse
import time
from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from timing import add_interleave_arguments, interleaved_rates, median_iqr

from sb3_sera import MASAC, SERASAC
from sb3_sera.common.compiled import CompileMode
from sb3_sera.common.mujoco_log import route_mujoco_warnings
from sb3_sera.ctde.actors import CTDEActor
from sb3_sera.ctde.policies import MASACPolicy
from sb3_sera.sera.policies import SERACTDEPolicy


class LoopSERAPolicy(SERACTDEPolicy):
    """SERASAC's CTDE policy with one SB3 actor per agent, run in a loop."""

    ctde_actor_class = CTDEActor


class LoopMASACPolicy(MASACPolicy):
    """MASAC's policy with one SB3 actor per agent, run in a loop."""

    ctde_actor_class = CTDEActor


def build_model(name: str, args: argparse.Namespace, compile_mode: CompileMode) -> tuple[BaseAlgorithm, float]:
    """The model ``name`` with its buffer filled and three gradient steps taken; the seconds those steps took."""
    common: dict[str, Any] = dict(seed=args.seed, learning_starts=args.learning_starts, device=args.device)
    multi_agent = gym.make(args.ma_env)
    policies: dict[str, tuple[type[BaseAlgorithm], Any, Any, dict[str, Any]]] = {
        "SERASAC": (SERASAC, "MlpPolicy", args.env, {}),
        "SERASAC-MA": (SERASAC, "CTDEPolicy", multi_agent, {}),
        "SERASAC-MA-loop": (SERASAC, LoopSERAPolicy, multi_agent, {}),
        "SERASAC+compile": (SERASAC, "MlpPolicy", args.env, dict(compile_update=compile_mode)),
        "SERASAC-MA+compile": (SERASAC, "CTDEPolicy", multi_agent, dict(compile_update=compile_mode)),
        "MASAC": (MASAC, "CTDEPolicy", multi_agent, {}),
        "MASAC-loop": (MASAC, LoopMASACPolicy, multi_agent, {}),
        "MASAC+compile": (MASAC, "CTDEPolicy", multi_agent, dict(compile_update=compile_mode)),
    }
    algo, policy, env, kwargs = policies[name]
    model = algo(policy, env, **common, **kwargs)
    model.learn(args.learning_starts)
    start = time.perf_counter()
    model.train(gradient_steps=3, batch_size=model.batch_size)  # type: ignore[attr-defined]
    return model, time.perf_counter() - start


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_interleave_arguments(parser, blocks=10, block_steps=100, warmup_blocks=2, unit="learn() steps")
    parser.add_argument("--ma-env", default="sb3_sera/HalfCheetah-6x1-v0", help="the multi-agent task")
    parser.add_argument("--threads", type=int, default=th.get_num_threads(), help="torch threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", help="torch device of all models, e.g. cuda")
    parser.add_argument("--compile", action="store_true", help="also time the multi-agent SERASAC compiled")
    parser.add_argument("--cuda-graphs", action="store_true", help="with --compile: compile_update='reduce-overhead'")
    parser.add_argument(
        "--models",
        nargs="+",
        default=["SERASAC", "SERASAC-MA", "SERASAC-MA-loop", "MASAC", "MASAC-loop"],
        choices=["SERASAC", "SERASAC-MA", "SERASAC-MA-loop", "MASAC", "MASAC-loop"],
        help="the models to time (SERASAC, the reference, is always timed)",
    )
    args = parser.parse_args()

    import sb3_sera.ctde.tasks  # noqa: F401  (registers the multi-agent ids)

    th.set_num_threads(args.threads)
    compiled = ["SERASAC+compile", "SERASAC-MA+compile", "MASAC+compile"] if args.compile else []
    names = list(dict.fromkeys(["SERASAC", *args.models, *compiled]))
    compile_mode: CompileMode = "reduce-overhead" if args.cuda_graphs else True
    models, first_steps = {}, {}
    for name in names:
        models[name], first_steps[name] = build_model(name, args, compile_mode)
    device = th.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(f"{args.env} and {args.ma_env}, {args.threads} torch thread(s), torch {th.__version__}, {device}")
    print(f"{'model':<20} {'learn() steps/s':>16} {'IQR':>13} {'x SERASAC':>10} {'first 3 steps (s)':>18}")
    rates = interleaved_rates(models, "learn", args.blocks, args.block_steps, None, args.warmup_blocks)
    stats = {name: median_iqr(values) for name, values in rates.items()}
    for name, (median, low, high) in stats.items():
        ratio = median / stats["SERASAC+compile" if name.endswith("+compile") else "SERASAC"][0]
        print(f"{name:<20} {median:>16.1f} {f'{low:.1f}-{high:.1f}':>13} {ratio:>10.2f} {first_steps[name]:>18.1f}")


if __name__ == "__main__":
    main()
