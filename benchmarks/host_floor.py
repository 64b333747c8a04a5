"""
The host floor of ``learn()``: what an env step costs when the networks have nothing to compute (actor and critics
of one hidden layer of 4, batch 8), so that what is left is the work around the arithmetic: acting, the env, the
replay buffer, ``train()``'s own code and the call of the step. On a GPU this floor caps the rate whatever the device
computes; on a CPU it can be measured without one.

The models, interleaved in one process (alternating blocks of ``learn()``, one gradient step per env step, so that
machine noise hits them alike): SB3's SAC eager, SERASAC eager and ``compile_update=True`` on ``--env``, and MASAC
eager and compiled on the CTDE task ``--ma-env`` (compiled with ``"reduce-overhead"`` on a GPU, ``--device cuda``;
the device check's ``floor`` section runs this there). For each, the median milliseconds an env step over the blocks (with
the interquartile range), its ratio to SB3 SAC's, and the split of an env step, each part timed by a clock around the
call that does it:

- ``acting``: ``_sample_action`` (SB3's ``predict`` path, or the algorithm's own);
- ``env``: ``VecEnv.step`` (the monitor included);
- ``buffer``: the replay buffer's ``add`` and ``sample``;
- ``train() host``: ``train()`` without the batches' sampling and the step itself (the preamble: training mode, the
  learning-rate schedules; the step's arguments; logging);
- ``step``: the gradient step: the compiled step's calls (the Python around Inductor's code included), or eager
  ``train()``'s steps (``train()`` without its preamble and sampling);
- ``read``: reading the compiled steps' values back (once per log interval in ``learn()``);
- ``rest``: the rest of SB3's loop (callbacks, storing the transition beside ``add``, the episode bookkeeping).

Then the host reads an env step (:mod:`host_reads`) over an untimed block; with ``--profile N`` the ``N``
functions with the most own time (``cProfile``, which inflates every Python call) over ``--profile-steps`` steps of
each compiled model; and with ``--step-calls N`` each compiled model's built step alone, ``N`` calls on one batch,
with Dynamo's guards evaluated (as ``learn()`` calls it) and skipped (``torch.compiler.set_stance`` with
``skip_guard_eval_unsafe=True``), interleaved with a check in Python of the layout of the tensors it reads: what
the guards cost, and the least a sound skip of them would cost instead. The library never skips them (a skipped
guard misses a change the graph depends on).

    OMP_NUM_THREADS=1 python benchmarks/host_floor.py
    OMP_NUM_THREADS=1 python benchmarks/host_floor.py --blocks 5 --block-steps 200 --profile 15 --step-calls 2000
"""

import argparse
import cProfile
import pstats
import time
from collections import defaultdict
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from host_reads import HostReads
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from timing import interleaved, median_iqr

from sb3_sera import MASAC, SERASAC
from sb3_sera.common.compiled import CompiledUpdate
from sb3_sera.common.compiled.modes import tracing
from sb3_sera.common.mujoco_log import route_mujoco_warnings

#: The parts of an env step, in the order the table prints them
PARTS = ("acting", "env", "buffer", "train() host", "step", "read", "rest")

#: Interleaved rounds of ``--step-calls`` calls each, per compiled model and kind (:func:`step_call_rows`)
STEP_CALL_ROUNDS = 5

#: Networks with nothing to compute: one hidden layer of 4 for the actor and each critic
TINY: dict[str, Any] = dict(net_arch=[4])


def floor_models(env_id: str, ma_env_id: str, device: str, seed: int = 0) -> dict[str, Callable[[], BaseAlgorithm]]:
    """
    The floor's models, by name, each a constructor: compute-free networks, batch 8, SB3's other defaults; compiled
    with ``compile_update=True``, or ``"reduce-overhead"`` (CUDA graphs) on a GPU.
    """
    common: dict[str, Any] = dict(batch_size=8, learning_starts=100, device=device, seed=seed, verbose=0)
    critics = dict(critic_archs=[[4]] * 5)
    mode: Any = "reduce-overhead" if device.startswith("cuda") else True
    return {
        "SB3 SAC eager": lambda: SAC("MlpPolicy", env_id, policy_kwargs=TINY, **common),
        "SERASAC eager": lambda: SERASAC("MlpPolicy", env_id, policy_kwargs={**TINY, **critics}, **common),
        "SERASAC compiled": lambda: SERASAC(
            "MlpPolicy", env_id, policy_kwargs={**TINY, **critics}, compile_update=mode, **common
        ),
        "MASAC eager": lambda: MASAC("CTDEPolicy", gym.make(ma_env_id), policy_kwargs=TINY, **common),
        "MASAC compiled": lambda: MASAC("CTDEPolicy", gym.make(ma_env_id), policy_kwargs=TINY, compile_update=mode, **common),
    }


class Split:
    """
    Clocks around the calls an env step of ``learn()`` makes (see the module's docstring), set on one model's
    instance; :meth:`parts` gives each part's share of a block.
    """

    def __init__(self, model: BaseAlgorithm):
        self.seconds: dict[str, float] = defaultdict(float)
        self._in_train = False
        self._clock(model, "_sample_action", "acting")
        assert model.env is not None
        self._clock(model.env, "step", "env")
        buffer = model.replay_buffer  # type: ignore[attr-defined]
        self._clock(buffer, "add", "add")
        self._clock(buffer, "sample", "sample")
        if isinstance(model, CompiledUpdate):
            self._clock(model, "read_pending_steps", "read")
        self.compiled = isinstance(model, CompiledUpdate) and model._compiled_step is not None
        if self.compiled:
            self._clock(model, "_compiled_step", "step")
        else:
            # Eager: the preamble is the host's, the rest of train() (but the sampling) the step's
            self._clock(model.policy, "set_training_mode", "preamble")
            self._clock(model, "_update_learning_rate", "preamble")
        self._clock(model, "train", "train")

    def _clock(self, owner: Any, attribute: str, part: str) -> None:
        """Time ``owner.attribute``'s calls under ``part`` (``"<part> in train"`` where ``train()`` made them)."""
        call = getattr(owner, attribute)

        def timed(*args: Any, **kwargs: Any) -> Any:
            outer = self._in_train
            self._in_train = outer or part == "train"
            start = time.perf_counter()
            try:
                return call(*args, **kwargs)
            finally:
                self.seconds[f"{part} in train" if outer else part] += time.perf_counter() - start
                self._in_train = outer

        setattr(owner, attribute, timed)

    def reset(self) -> None:
        """Start the clocks again."""
        self.seconds.clear()

    def parts(self, total: float, steps: int) -> dict[str, float]:
        """Each part's milliseconds per env step, of a block of ``steps`` env steps that took ``total`` seconds."""
        seconds = self.seconds
        train, sample = seconds["train"], seconds["sample in train"]
        read = seconds["read"] + seconds["read in train"]
        if self.compiled:
            step = seconds["step in train"]
            host = train - sample - step - seconds["read in train"]
        else:
            host = seconds["preamble in train"]
            step = train - sample - host - seconds["read in train"]
        within = {
            "acting": seconds["acting"],
            "env": seconds["env"],
            "buffer": seconds["add"] + sample,
            "train() host": host,
            "step": step,
            "read": read,
        }
        within["rest"] = total - seconds["acting"] - seconds["env"] - seconds["add"] - train - seconds["read"]
        return {part: 1e3 * value / steps for part, value in within.items()}


def timed_block(model: BaseAlgorithm, split: Split, steps: int) -> tuple[float, dict[str, float]]:
    """One block of ``learn(steps)``: the milliseconds an env step, and the split's parts."""
    split.reset()
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    total = time.perf_counter() - start
    return 1e3 * total / steps, split.parts(total, steps)


def build(constructor: Callable[[], BaseAlgorithm]) -> tuple[BaseAlgorithm, Split]:
    """A model with its buffer filled, a few gradient steps taken (a compiled step compiles here), and its clocks."""
    model = constructor()
    model.learn(model.learning_starts + 50)  # type: ignore[attr-defined]
    return model, Split(model)


def floor_table(
    models: dict[str, tuple[BaseAlgorithm, Split]], blocks: int, block_steps: int, warmup_blocks: int = 1
) -> list[str]:
    """
    The floor's rows, Markdown: each model's median ms an env step (IQR), its ratio to the first model's, the median
    of each part over the blocks, and the host reads an env step (an untimed block after the timed ones).
    """
    names = list(models)
    measured = interleaved(models, lambda pair: timed_block(*pair, block_steps), blocks, warmup_blocks)
    totals = {name: [total for total, _ in measured[name]] for name in names}
    parts = {name: [split for _, split in measured[name]] for name in names}
    reference = float(np.median(totals[names[0]]))
    rows = [
        f"| model | ms an env step (IQR) | x {names[0]} | {' | '.join(PARTS)} | host reads an env step |",
        "|---|---|---|" + "---|" * len(PARTS) + "---|",
    ]
    for name in names:
        model = models[name][0]
        with HostReads() as reads:
            model.learn(block_steps, reset_num_timesteps=False)
        median, low, high = median_iqr(totals[name])
        cells = [f"{np.median([split[part] for split in parts[name]]):.3f}" for part in PARTS]
        rows.append(
            f"| {name} | {median:.3f} ({low:.3f}-{high:.3f}) | {median / reference:.3f} | {' | '.join(cells)} "
            f"| {reads.count / block_steps:.2f} |"
        )
    return rows


def profile_rows(model: BaseAlgorithm, steps: int, top: int) -> list[str]:
    """The ``top`` functions by own time (``cProfile``) over ``learn(steps)``, microseconds an env step."""
    profiler = cProfile.Profile()
    profiler.enable()
    model.learn(steps, reset_num_timesteps=False)
    profiler.disable()
    stats = pstats.Stats(profiler)
    table: dict[tuple[str, int, str], tuple[Any, ...]] = stats.stats  # type: ignore[attr-defined]
    ranked = sorted(table.items(), key=lambda item: item[1][2], reverse=True)[:top]
    return [
        f"  {1e6 * entry[2] / steps:8.1f} us {entry[1] / steps:6.1f} calls  {function} ({file.rsplit('/', 2)[-1]}:{line})"
        for (file, line, function), entry in ranked
    ]


def compiled_models(models: dict[str, tuple[BaseAlgorithm, Split]]) -> dict[str, BaseAlgorithm]:
    """The models of :func:`build` whose gradient step is compiled, by name."""
    return {
        name: model
        for name, (model, _) in models.items()
        if isinstance(model, CompiledUpdate) and model._compiled_step is not None
    }


def step_call_rows(models: Mapping[str, BaseAlgorithm], calls: int, rounds: int = STEP_CALL_ROUNDS) -> list[str]:
    """
    The compiled models' built step alone, Markdown rows: the median ms a call over ``rounds`` interleaved rounds of
    ``calls`` calls on one batch, a step that changes nothing (``healthy`` false), with Dynamo's guards evaluated and
    with them skipped (a measurement only: see the module's docstring); and beside them what a check in Python of
    the identity and layout of the tensors the step reads (the policy's parameters and buffers, the Adam states)
    costs, the least that skipping the guards soundly would have to do instead at every call.
    """

    def time_layout_check(model: BaseAlgorithm) -> float:
        assert isinstance(model, CompiledUpdate)
        states = [tensor for plan in model._probe_arguments()["states"] for state in plan for tensor in state]
        tensors = [*model.policy.parameters(), *model.policy.buffers(), *states]

        def layout() -> list[tuple[Any, ...]]:
            return [(id(t), t.shape, t.dtype, t.device, t.requires_grad, t.stride()) for t in tensors]

        checked = layout()
        start = time.perf_counter()
        for _ in range(calls):
            assert layout() == checked
        return 1e3 * (time.perf_counter() - start) / calls

    def time_calls(model: BaseAlgorithm, skip_guards: bool) -> float:
        assert isinstance(model, CompiledUpdate) and model._compiled_step is not None
        step, batch, arguments = model._compiled_step, model._sample_batch(model.batch_size), model._probe_arguments()
        graphs = model.compile_update == "reduce-overhead"
        with tracing(), th.compiler.set_stance("default", skip_guard_eval_unsafe=skip_guards):
            start = time.perf_counter()
            for _ in range(calls):
                if graphs:
                    th.compiler.cudagraph_mark_step_begin()
                step(batch, **arguments)
            if model.device.type == "cuda":
                th.cuda.synchronize()
            return 1e3 * (time.perf_counter() - start) / calls

    kinds = ("call", "guards skipped", "layout check")
    timers: dict[str, Callable[[BaseAlgorithm], float]] = {
        "call": lambda model: time_calls(model, False),
        "guards skipped": lambda model: time_calls(model, True),
        "layout check": time_layout_check,
    }
    variants = {f"{name}, {kind}": (model, timers[kind]) for name, model in models.items() for kind in kinds}
    measured = interleaved(variants, lambda variant: variant[1](variant[0]), rounds, warmup_blocks=1)
    rows = [
        "| model | the step's call, ms (IQR) | guards skipped, ms (IQR) | its tensors' layout checked in Python, ms (IQR) |",
        "|---|---|---|---|",
    ]
    for name in models:
        cells = ["{:.3f} ({:.3f}-{:.3f})".format(*median_iqr(measured[f"{name}, {kind}"])) for kind in kinds]
        rows.append(f"| {name} | {' | '.join(cells)} |")
    return rows


def main() -> None:
    route_mujoco_warnings()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--ma-env", default="sb3_sera/SimpleSpread-v0", help="the CTDE task of the multi-agent rows")
    parser.add_argument("--blocks", type=int, default=7, help="timed blocks per model")
    parser.add_argument("--block-steps", type=int, default=300, help="learn() steps per block")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--models", nargs="+", help="the models to time (default: all; the first is the reference)")
    parser.add_argument("--profile", type=int, default=0, help="then the top N functions of each compiled model")
    parser.add_argument("--profile-steps", type=int, default=1000)
    parser.add_argument("--step-calls", type=int, default=0, help="then N calls of each compiled model's step alone")
    args = parser.parse_args()
    import sb3_sera.ctde.tasks  # noqa: F401  (registers the multi-agent ids)

    th.set_num_threads(args.threads)
    constructors = floor_models(args.env, args.ma_env, args.device)
    names = args.models or list(constructors)
    unknown = sorted(set(names) - set(constructors))
    if unknown:
        parser.error(f"unknown model(s) {unknown}: choose from {list(constructors)}")
    models = {name: build(constructors[name]) for name in names}
    device = th.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(f"{args.env} and {args.ma_env}, {args.threads} torch thread(s), torch {th.__version__}, {device}")
    print("\n".join(floor_table(models, args.blocks, args.block_steps)))
    compiled = compiled_models(models)
    for name, model in compiled.items():
        if args.profile:
            print(f"\n{name}: top {args.profile} by own time, cProfile, {args.profile_steps} env steps")
            print("\n".join(profile_rows(model, args.profile_steps, args.profile)))
    if args.step_calls and compiled:
        print(
            f"\nThe compiled step's call alone, {args.step_calls} calls a round, medians of {STEP_CALL_ROUNDS} "
            "interleaved rounds"
        )
        print("\n".join(step_call_rows(compiled, args.step_calls)))


if __name__ == "__main__":
    main()
