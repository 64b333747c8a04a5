"""
Floating-point work of the matrix products in one gradient step of SAC and SERASAC, and the rate they run at.

Counts the FLOPs of ``aten::mm`` and ``aten::addmm`` with ``torch.profiler`` (``with_flops=True``) over
``--steps`` gradient steps of each model, built with its defaults on the task, and reports FLOPs per step, the
time the products took per step (profiler clock) and their rate:

    python benchmarks/flops.py --env HalfCheetah-v5 --steps 20
"""

import argparse

import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from torch.profiler import ProfilerActivity, profile

from sb3_sera import SERASAC
from sb3_sera.common.mujoco_log import route_mujoco_warnings

MATMULS = ("aten::mm", "aten::addmm")


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--steps", type=int, default=20, help="profiled gradient steps per model")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--learning-starts", type=int, default=300)
    parser.add_argument("--threads", type=int, default=th.get_num_threads(), help="torch threads (default: torch's)")
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    print(f"{args.env}, batch {args.batch_size}, {args.threads} torch thread(s), torch {th.__version__}")
    print(f"{'algorithm':<9} {'matmul GFLOP/step':>18} {'matmul ms/step':>15} {'GFLOP/s':>8}")
    work = {}
    for name, algo in (("SAC", SAC), ("SERASAC", SERASAC)):
        model: BaseAlgorithm = algo("MlpPolicy", args.env, seed=0, learning_starts=args.learning_starts)
        model.learn(args.learning_starts)
        model.train(gradient_steps=3, batch_size=args.batch_size)  # type: ignore[attr-defined]
        with profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
            model.train(gradient_steps=args.steps, batch_size=args.batch_size)  # type: ignore[attr-defined]
        events = [event for event in prof.key_averages() if event.key in MATMULS]
        flops = sum(event.flops for event in events) / args.steps
        seconds = sum(event.self_cpu_time_total for event in events) / 1e6 / args.steps
        work[name] = flops
        print(f"{name:<9} {flops / 1e9:>18.3f} {seconds * 1e3:>15.2f} {flops / seconds / 1e9:>8.1f}")
    print(f"SERASAC / SAC matmul work: {work['SERASAC'] / work['SAC']:.2f}x")


if __name__ == "__main__":
    main()
