"""
Gradient steps per second of SERASAC against stock SB3 SAC, interleaved in one process.

Both models are built with their defaults on the same task, their replay buffers filled with
``--learning-starts`` random transitions, then timed in alternating blocks so that machine noise hits both alike:

- ``train``: ``model.train(block, batch_size)`` only (the gradient step);
- ``learn``: ``model.learn(block)``, environment steps and one gradient step per environment step (SB3 defaults).

With ``--compile``, a third model, SERASAC with its whole gradient step compiled (``compile_update=True``, or
``"reduce-overhead"``, replayed as a CUDA graph, with ``--cuda-graphs``), joins the interleave, and the script prints
how many graphs and graph breaks Dynamo finds in that step (one graph, no break, when it compiles whole).
``--device cuda`` runs all three on a GPU. With ``--device-buffer``, the compiled SERASAC drawing its batches from a
:class:`~sb3_sera.common.device_buffer.DeviceReplayBuffer` joins too (``SERASAC+compile+device``).

Each figure is the median over blocks, with the interquartile range; the ratio is SAC's median rate over
SERASAC's (the wall-time cost of SERASAC per gradient step, in units of SAC's).

    python benchmarks/train_speed.py --env HalfCheetah-v5 --blocks 15 --block-steps 100
    python benchmarks/train_speed.py --compile --device cuda --cuda-graphs
"""

import argparse
from functools import partial
from typing import Any

import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from timing import add_interleave_arguments, interleaved_rates, median_iqr

from sb3_sera import SERASAC, DeviceReplayBuffer
from sb3_sera.common.compiled import CompileMode, count_graph_breaks
from sb3_sera.common.mujoco_log import route_mujoco_warnings


def build_model(
    name: str, env_id: str, *, seed: int, learning_starts: int, batch_size: int, device: str, compile_mode: CompileMode
) -> BaseAlgorithm:
    common: dict[str, Any] = dict(seed=seed, learning_starts=learning_starts, device=device)
    if name == "SAC":
        model: BaseAlgorithm = SAC("MlpPolicy", env_id, **common)
    else:
        compile_update = compile_mode if name.startswith("SERASAC+") else False
        if name.endswith("+device"):
            common["replay_buffer_class"] = DeviceReplayBuffer
        model = SERASAC("MlpPolicy", env_id, compile_update=compile_update, **common)
    # Fill the replay buffer with random transitions (no gradient step before learning_starts), then take a few
    # untimed gradient steps (compilation happens here)
    model.learn(learning_starts)
    model.train(gradient_steps=3, batch_size=batch_size)  # type: ignore[attr-defined]
    return model


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_interleave_arguments(parser, blocks=15, block_steps=100, warmup_blocks=2)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--threads", type=int, default=th.get_num_threads(), help="torch threads (default: torch's)")
    parser.add_argument("--modes", nargs="+", default=["train", "learn"], choices=["train", "learn"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compile", action="store_true", help="also time SERASAC with its gradient step compiled")
    parser.add_argument("--cuda-graphs", action="store_true", help="with --compile: compile_update='reduce-overhead'")
    parser.add_argument("--device", default="cpu", help="torch device of all models, e.g. cuda")
    parser.add_argument(
        "--device-buffer", action="store_true", help="with --compile: also time it with the replay buffer on the device"
    )
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    if args.device_buffer and not args.compile:
        parser.error("--device-buffer times the compiled step with a DeviceReplayBuffer: give it with --compile")
    names = ["SAC", "SERASAC", *(["SERASAC+compile"] if args.compile else [])]
    names += ["SERASAC+compile+device"] if args.device_buffer else []
    compile_mode: CompileMode = "reduce-overhead" if args.cuda_graphs else True
    build = partial(
        build_model,
        env_id=args.env,
        seed=args.seed,
        learning_starts=args.learning_starts,
        batch_size=args.batch_size,
        device=args.device,
        compile_mode=compile_mode,
    )
    models = {name: build(name) for name in names}
    device = th.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(f"{args.env}, batch {args.batch_size}, {args.threads} torch thread(s), torch {th.__version__}, {device}")
    print(f"{'mode':<6} {'algorithm':<23} {'steps/s (median)':>17} {'IQR':>15}  ratio (SAC rate / rate)")
    for mode in args.modes:
        rates = interleaved_rates(models, mode, args.blocks, args.block_steps, args.batch_size, args.warmup_blocks)
        stats = {name: median_iqr(values) for name, values in rates.items()}
        for name, (median, low, high) in stats.items():
            ratio = stats["SAC"][0] / median
            print(f"{mode:<6} {name:<23} {median:>17.1f} {f'{low:.1f}-{high:.1f}':>15}  {ratio:.2f}x")
    if args.compile:
        # After the timing: tracing again for the count resets Dynamo's compiled code
        compiled = models["SERASAC+compile"]
        assert isinstance(compiled, SERASAC) and compiled.replay_buffer is not None
        batch = compiled.replay_buffer.sample(args.batch_size)
        graphs, breaks = count_graph_breaks(compiled, compiled._gradient_step_graph, batch)
        print(f"compiled SERASAC step (compile_update={compile_mode!r}): {graphs} graph(s), {breaks} graph break(s)")


if __name__ == "__main__":
    main()
