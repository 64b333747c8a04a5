"""
Where a ``learn()`` step spends its time: SB3 SAC, SERASAC eager and SERASAC with ``compile_update=True`` on the same
task, after ``learning_starts``, each profiled with ``cProfile`` over ``--steps`` environment steps (one gradient step
each, SB3's defaults).

The time is split into the parts of SB3's off-policy loop, each the cumulative time of the call that does it (no part
holds another): action selection (``_sample_action``), the environment step (``VecEnv.step``, the monitor included),
the replay buffer's ``add`` and ``sample``, the gradient step (``train`` without the sample, the host read and the
logging it does), reading the step's values back from the device (``read_steps``, the compiled step's one read per
``train()`` call), logging (``Logger.record`` and ``dump``), the callbacks' ``on_step``, and the rest of the loop.
``cProfile`` adds its own cost to every Python call, so the shares are a guide to where the time goes and the totals
are not rates.

``--ops N`` then profiles ``--op-steps`` gradient steps (``train()`` calls of one step) of each model with
``torch.profiler`` and prints the matrix products' share and the N operations with the most self CPU time per step;
the compiled graph's kernels are recorded one by one (Inductor's ``cpp.enable_kernel_profile``).

    OMP_NUM_THREADS=1 python benchmarks/learn_profile.py --env HalfCheetah-v5 --steps 1000
    OMP_NUM_THREADS=1 python benchmarks/learn_profile.py --models SAC SERASAC+compile --steps 100 --ops 12
"""

import argparse
import cProfile
import pstats
from collections import Counter
from typing import Any

import torch as th
import torch._inductor.config
from stable_baselines3.common.base_class import BaseAlgorithm
from train_speed import build_model

from sb3_sera.common.mujoco_log import route_mujoco_warnings

#: The parts of a ``learn()`` step but the gradient step: (name, the functions whose cumulative time it is, by file
#: and name)
PARTS: list[tuple[str, list[tuple[str, str]]]] = [
    ("action selection", [("off_policy_algorithm.py", "_sample_action")]),
    ("env step", [("base_vec_env.py", "step")]),
    ("buffer add", [("buffers.py", "add")]),
    ("buffer sample", [("buffers.py", "sample")]),
    ("host read", [("compiled/base.py", "read_steps")]),
    ("logging", [("logger.py", "record"), ("logger.py", "dump")]),
    ("callbacks", [("callbacks.py", "on_step")]),
]


#: The functions that log from inside ``train()`` (their ``Logger.record`` calls are logging, not the gradient step)
TRAIN_LOGGERS = ("train", "_train_compiled", "_end_train", "record_means")


def _cumulative(table: dict[tuple[str, int, str], tuple[Any, ...]], functions: list[tuple[str, str]]) -> float:
    return sum(
        entry[3]
        for (file, _, function), entry in table.items()
        if any(file.endswith(suffix) and function == name for suffix, name in functions)
    )


def parts(stats: pstats.Stats, total: float) -> dict[str, float]:
    """Each part's cumulative seconds, the gradient step's, and the rest of ``total``."""
    table: dict[tuple[str, int, str], tuple[Any, ...]] = stats.stats  # type: ignore[attr-defined]
    seconds = {part: _cumulative(table, functions) for part, functions in PARTS}
    logged_in_train = sum(
        caller_entry[3]
        for (file, _, function), entry in table.items()
        if file.endswith("logger.py") and function == "record"
        for (_, _, caller), caller_entry in entry[4].items()
        if caller in TRAIN_LOGGERS
    )
    train = _cumulative(table, [("sac.py", "train"), ("sera.py", "train")])
    seconds["gradient step"] = train - seconds["buffer sample"] - seconds["host read"] - logged_in_train
    seconds["rest of the loop"] = total - sum(seconds.values())
    return seconds


def print_ops(name: str, model: BaseAlgorithm, steps: int, top: int) -> None:
    """The matrix products' self CPU time per gradient step and the ``top`` operations by self CPU time."""
    with th.profiler.profile(activities=[th.profiler.ProfilerActivity.CPU]) as profile:
        for _ in range(steps):
            model.train(gradient_steps=1, batch_size=256)  # type: ignore[attr-defined]
    self_ms: Counter[str] = Counter()
    calls: Counter[str] = Counter()
    for event in profile.key_averages():
        self_ms[event.key] += event.self_cpu_time_total / 1e3 / steps
        calls[event.key] += event.count / steps
    total = sum(self_ms.values())
    products = self_ms["aten::addmm"] + self_ms["aten::mm"]
    print(f"{name}: {total:.2f} ms self CPU time per step, matrix products (addmm, mm) {products:.2f} ms")
    for key, value in self_ms.most_common(top):
        print(f"  {key[:70]:<70} {value:7.3f} ms {calls[key]:6.1f} calls")


def main() -> None:
    route_mujoco_warnings()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--steps", type=int, default=1000, help="profiled learn() steps per model")
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--models", nargs="+", default=["SAC", "SERASAC", "SERASAC+compile"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ops", type=int, default=0, help="then list this many operations by torch.profiler")
    parser.add_argument("--op-steps", type=int, default=100, help="gradient steps profiled for --ops")
    args = parser.parse_args()
    th.set_num_threads(1)
    # Each kernel of a compiled graph its own profiler event (set before anything compiles)
    torch._inductor.config.cpp.enable_kernel_profile = args.ops > 0
    print(f"{args.env}, {args.steps} learn() steps per model after {args.learning_starts}, one torch thread")
    columns = {}
    models = {}
    for name in args.models:
        model = build_model(
            name,
            args.env,
            seed=args.seed,
            learning_starts=args.learning_starts,
            batch_size=256,
            device="cpu",
            compile_mode=True,
        )
        profiler = cProfile.Profile()
        profiler.enable()
        model.learn(args.steps, reset_num_timesteps=False)
        profiler.disable()
        stats = pstats.Stats(profiler)
        total = stats.total_tt  # type: ignore[attr-defined]
        columns[name] = (total, parts(stats, total))
        models[name] = model
    names = list(columns)
    print(f"{'part':<18}" + "".join(f"{name:>24}" for name in names))
    for part in [*(part for part, _ in PARTS), "gradient step", "rest of the loop"]:
        cells = [
            f"{1e3 * seconds[part] / args.steps:7.3f} ms {100 * seconds[part] / total:5.1f}%"
            for total, seconds in columns.values()
        ]
        print(f"{part:<18}" + "".join(f"{cell:>24}" for cell in cells))
    print(f"{'total per step':<18}" + "".join(f"{1e3 * total / args.steps:>21.3f} ms" for total, _ in columns.values()))
    for name, model in models.items() if args.ops else ():
        print_ops(name, model, args.op_steps, args.ops)


if __name__ == "__main__":
    main()
