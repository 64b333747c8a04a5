"""
The GPU check (``benchmarks/device_check.sh`` installs the carried wheels and runs this): on one CUDA device, in one
process, a table of

- ``cudagraphs``: whether the compiled gradient steps with ``compile_update="reduce-overhead"`` replay as CUDA graphs:
  Inductor's count of skipped graphs (``counters["inductor"]["cudagraph_skips"]``) after compiling and running them,
  and any :class:`~sb3_sera.common.compiled.CUDAGraphSkipWarning` with its reason;
- ``compiled vs eager``: the largest parameter difference between eager and compiled SERASAC on CUDA after 1, 40 and
  100 gradient steps on the same batches and draws (``compiled_vs_eager.py``, every generator of the device reset);
  with ``order``, also compiled without chaining the step's random draws (``--against compiled-unordered``: whether
  Inductor's scheduler alone keeps their order);
- ``draws``: whether the compiled step's random draws are eager's on the device: two actor draws
  (``Normal.rsample``) eager and compiled (``compile_update=True`` and, on CUDA, ``"reduce-overhead"``) from the same
  generator state, and compiled against eager SERASAC again with every normal draw fixed to the same numbers in both
  (``--against compiled-fixed-draws``): if the difference stays, the draws are not its cause; and one step of eager,
  of eager with its two draws taken in the other order, and of compiled SERASAC from the same state
  (``compiled_vs_eager.step_draws_account``): which eager order the compiled step's draws follow;
- ``gradients``: eager and compiled SERASAC's gradients on CUDA, each step from the same parameters
  (``compiled_vs_eager.gradient_differences``): their largest relative difference, and whether the parameters that
  part after one step are those whose gradient is at rounding's scale (Adam's first step moves every element by about
  its learning rate, whatever the gradient's size);
- ``learn()`` steps per second, interleaved: SB3 SAC, SERASAC eager, ``compile_update=True`` and
  ``"reduce-overhead"`` (its batches from a ``DeviceReplayBuffer``), SBX's SAC with five critics of [256, 256] where
  ``sbx`` imports, on ``--env``; SERASAC eager and ``"reduce-overhead"`` and MASAC eager and ``"reduce-overhead"`` on
  ``--ma-env`` (the CTDE policy, the agents' actors stacked);
- ``split``: per env step of SB3 SAC and of SERASAC ``"reduce-overhead"`` (``compile_update=True`` on a CPU), after
  the speed section and an untimed ``learn()`` of as many steps: ``learn()``, ``train()`` alone (one gradient step a
  call), the rest (acting, env step, buffer, callbacks, logging), the compiled step's replay alone (``--split-steps``
  replays back to back, timed with CUDA events), an action (``_sample_action``) eager and through the compiled
  actor, and the host reads per env step (`benchmarks/host_reads.py`);
- ``many``: 1, 4 and 8 processes (``--processes``) of SERASAC ``"reduce-overhead"`` learning on ``--env`` on the one
  device at once: each one's ``learn()`` rate and their total, against one process's;
- ``floor``: the host floor (``host_floor.py``): SB3 SAC, SERASAC and MASAC at compute-free networks on Pendulum-v1
  and ``--ma-env``, the milliseconds an env step and its split (acting, env, buffer, ``train()``'s host code, the
  step, the read), a table of its own after the others, then each compiled model's step alone (``--split-steps``
  calls) with Dynamo's guards and without them, beside a check of its tensors' layout in Python.

Each rate is the median of ``--blocks`` blocks of ``--block-steps`` steps, with its ratio to SB3 SAC's rate (the
single-agent rows) or to eager SERASAC's on the multi-agent task (the multi-agent rows). Every section takes about 13
minutes on an H200 (2026-11-27: the sections up to ``speed`` but ``draws`` 8.3 minutes, builds and install included;
``split`` and ``many`` 2.2 more on the machine still warm; ``draws`` with ``equality`` and ``split``, 100 equality
steps, 3.7 minutes on a fresh machine), more than one call of the lent machine may run (10 minutes): run it as two
calls, ``--sections cudagraphs equality order gradients speed`` and ``--sections draws split many``.

    bash benchmarks/device_check.sh                       # the wheels in .whl/, see docs/guide/developer.md
    python benchmarks/device_check.py --sections speed --blocks 5
    python benchmarks/device_check.py --device cpu --env Pendulum-v1 --blocks 1 --block-steps 2   # a smoke run
"""

import argparse
import ast
import importlib.util
import multiprocessing
import time
import warnings
from collections.abc import Callable
from functools import partial
from typing import Any

import compiled_vs_eager
import gymnasium as gym
import host_floor
import torch as th
from host_reads import HostReads
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer
from timing import interleaved_rates, median_iqr

from sb3_sera import MASAC, SERASAC
from sb3_sera.common.compiled import CompiledUpdate, CUDAGraphSkipWarning
from sb3_sera.common.mujoco_log import route_mujoco_warnings

SECTIONS = ("cudagraphs", "equality", "order", "draws", "gradients", "speed", "split", "many", "floor")


def single_agent_models(env_id: str, cuda: bool) -> dict[str, Callable[[dict[str, Any]], BaseAlgorithm]]:
    """The single-agent rows' constructors (SBX's where it is installed; CUDA graphs on a GPU only)."""
    table: dict[str, Callable[[dict[str, Any]], BaseAlgorithm]] = {
        "SB3 SAC eager": lambda kw: SAC("MlpPolicy", env_id, **kw),
        "SERASAC eager": lambda kw: SERASAC("MlpPolicy", env_id, **kw),
        "SERASAC compile_update=True": lambda kw: SERASAC("MlpPolicy", env_id, compile_update=True, **kw),
    }
    if cuda:
        table["SERASAC reduce-overhead"] = lambda kw: SERASAC("MlpPolicy", env_id, compile_update="reduce-overhead", **kw)
        table["SERASAC reduce-overhead, SB3's buffer"] = lambda kw: SERASAC(
            "MlpPolicy", env_id, compile_update="reduce-overhead", replay_buffer_class=ReplayBuffer, **kw
        )
    if importlib.util.find_spec("sbx") is not None:
        import sbx

        table["SBX SAC, 5 critics of [256, 256]"] = lambda kw: sbx.SAC(
            "MlpPolicy", env_id, policy_kwargs=dict(n_critics=5, net_arch=[256, 256]), **{**kw, "device": "auto"}
        )
    return table


def multi_agent_models(env_id: str, cuda: bool) -> dict[str, Callable[[dict[str, Any]], BaseAlgorithm]]:
    """The multi-agent rows' constructors (compiled with CUDA graphs on a GPU, without on a CPU)."""
    mode: Any = "reduce-overhead" if cuda else True
    name = "reduce-overhead" if cuda else "compile_update=True"
    return {
        "SERASAC-MA eager": lambda kw: SERASAC("CTDEPolicy", gym.make(env_id), **kw),
        f"SERASAC-MA {name}": lambda kw: SERASAC("CTDEPolicy", gym.make(env_id), compile_update=mode, **kw),
        "MASAC eager": lambda kw: MASAC("CTDEPolicy", gym.make(env_id), **kw),
        f"MASAC {name}": lambda kw: MASAC("CTDEPolicy", gym.make(env_id), compile_update=mode, **kw),
    }


def build(constructors: dict[str, Callable[[dict[str, Any]], BaseAlgorithm]], common: dict[str, Any]) -> dict[str, Any]:
    """Each model built, its buffer filled and a few steps learned (compilation and CUDA graph recording happen here)."""
    models = {}
    for name, constructor in constructors.items():
        start = time.perf_counter()
        model = constructor(common)
        model.learn(common["learning_starts"] + 10)
        print(f"built {name} in {time.perf_counter() - start:.0f} s", flush=True)
        models[name] = model
    return models


def speed_rows(models: dict[str, BaseAlgorithm], reference: str, args: argparse.Namespace) -> list[str]:
    """Interleaved ``learn()`` rates, as table rows with their ratio to ``reference``'s rate."""
    rates = interleaved_rates(models, "learn", args.blocks, args.block_steps, None, args.warmup_blocks)
    stats = {name: median_iqr(values) for name, values in rates.items()}
    return [
        f"| learn() steps/s | {name} | {median:.1f} ({low:.1f}-{high:.1f}) | {median / stats[reference][0]:.2f}x {reference} |"
        for name, (median, low, high) in stats.items()
    ]


def _timed(run: Callable[[], Any], cuda: bool) -> float:
    """Seconds ``run`` takes, the device's work included."""
    synchronize = th.cuda.synchronize if cuda else lambda: None
    synchronize()
    start = time.perf_counter()
    run()
    synchronize()
    return time.perf_counter() - start


def replay_ms(model: CompiledUpdate, replays: int, cuda: bool) -> float:
    """
    Milliseconds per replay of the compiled step alone, ``replays`` back to back on one batch, changing nothing
    (``healthy`` false): CUDA events around them on a GPU, the clock on a CPU.
    """
    assert model._compiled_step is not None
    batch, arguments = model._sample_batch(model.batch_size), model._probe_arguments()

    def replay() -> None:
        for _ in range(replays):
            if model.compile_update == "reduce-overhead":
                th.compiler.cudagraph_mark_step_begin()
            model._compiled_step(batch, **arguments)  # type: ignore[misc]

    replay()  # warm
    if not cuda:
        return 1e3 * _timed(replay, cuda) / replays
    start, end = th.cuda.Event(enable_timing=True), th.cuda.Event(enable_timing=True)
    start.record()
    replay()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / replays


def _train_calls(model: BaseAlgorithm, calls: int) -> None:
    """``calls`` calls of ``train()``, one gradient step each on the model's batch size."""
    for _ in range(calls):
        model.train(1, model.batch_size)  # type: ignore[attr-defined]


def split_rows(models: dict[str, BaseAlgorithm], steps: int, cuda: bool) -> list[str]:
    """Per env step: ``learn()``, ``train()`` alone, the rest, the compiled step's replay alone, and host reads."""
    rows = []
    for name, model in models.items():
        # Untimed first: on the H200 the first learn() after the build took 48.9 ms an env step where the speed
        # section's rate gives 4.2 ms (some one-off work: a recompilation or a CUDA graph's recording)
        model.learn(steps, reset_num_timesteps=False)
        with HostReads() as reads:
            learn = _timed(partial(model.learn, steps, reset_num_timesteps=False), cuda)
        train = _timed(partial(_train_calls, model, steps), cuda)
        cells = [
            f"learn() {1e3 * learn / steps:.2f} ms",
            f"train() alone {1e3 * train / steps:.2f} ms",
            f"the rest {1e3 * (learn - train) / steps:.2f} ms",
        ]
        if isinstance(model, CompiledUpdate) and model._compiled_step is not None:
            cells.append(f"the replay alone {replay_ms(model, steps, cuda):.3f} ms")
        cells.append(f"{reads.count / steps:.2f} host reads")
        rows.append(f"| per env step | {name} | {', '.join(cells)} | |")
    return rows


def _one_of_many(env_id: str, common: dict[str, Any], mode: Any, steps: int, barrier: Any, rates: Any, index: int) -> None:
    """One process of the ``many`` section: build, compile, wait for the others, then time ``learn(steps)``."""
    route_mujoco_warnings()
    th.set_num_threads(1)
    model = SERASAC("MlpPolicy", env_id, compile_update=mode, **{**common, "seed": index})
    model.learn(common["learning_starts"] + 20)
    barrier.wait()
    seconds = _timed(lambda: model.learn(steps, reset_num_timesteps=False), model.device.type == "cuda")
    rates.put(steps / seconds)


def many_rows(env_id: str, common: dict[str, Any], counts: list[int], steps: int, cuda: bool) -> list[str]:
    """``learn()`` rates of ``count`` processes learning at once on the one device, for each count."""
    context = multiprocessing.get_context("spawn")
    mode: Any = "reduce-overhead" if cuda else True
    rows, one = [], None
    for count in counts:
        barrier, rates = context.Barrier(count), context.Queue()
        processes = [
            context.Process(target=_one_of_many, args=(env_id, common, mode, steps, barrier, rates, index))
            for index in range(count)
        ]
        for process in processes:
            process.start()
        each = sorted(rates.get() for _ in processes)
        for process in processes:
            process.join()
        total = sum(each)
        one = total if one is None else one
        cells = f"each {', '.join(f'{rate:.1f}' for rate in each)}; total {total:.1f} steps/s"
        rows.append(f"| many runs | {count} process(es) at once | {cells} | {total / one:.2f}x one |")
    return rows


def emit(rows: list[str]) -> None:
    """Table rows, printed at once."""
    for row in rows:
        print(row, flush=True)


def main() -> None:
    route_mujoco_warnings()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--ma-env", default="sb3_sera/HalfCheetah-6x1-v0")
    parser.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    parser.add_argument("--blocks", type=int, default=3, help="timed blocks per model")
    parser.add_argument("--block-steps", type=int, default=200, help="learn() steps per block")
    parser.add_argument("--warmup-blocks", type=int, default=1, help="untimed rounds first")
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--equality-steps", type=int, default=100)
    parser.add_argument("--aggregations", nargs="+", default=["median"], help="actor aggregations compared")
    parser.add_argument("--device", default="cuda", help="cuda (the check), or cpu (a smoke run, without CUDA graphs)")
    parser.add_argument(
        "--policy-kwargs",
        type=ast.literal_eval,
        help="SERASAC's policy_kwargs in the equality, order, draws and gradients sections, a Python dict literal "
        "(default: SERASAC's own)",
    )
    parser.add_argument("--gradient-steps", type=int, default=100, help="steps of the gradients section")
    parser.add_argument("--split-steps", type=int, default=300, help="env steps (and replays) of the split section")
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 4, 8], help="process counts of many")
    parser.add_argument("--many-steps", type=int, default=500, help="learn() steps each process times")
    args = parser.parse_args()
    cuda = args.device.startswith("cuda")
    if cuda and not th.cuda.is_available():
        raise SystemExit("device_check.py checks a CUDA device, and torch sees none: run it on the GPU machine")
    import sb3_sera.ctde.tasks  # noqa: F401  (registers the multi-agent ids)

    started = time.perf_counter()
    common = dict(seed=0, learning_starts=args.learning_starts, device=args.device, verbose=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CUDAGraphSkipWarning)
        timed = {"cudagraphs", "speed"} & set(args.sections)
        single = build(single_agent_models(args.env, cuda), common) if timed | {"split"} & set(args.sections) else {}
        multi = build(multi_agent_models(args.ma_env, cuda), common) if timed else {}
    # Each row is printed as soon as it is measured, so that a run cut short by the machine's limit still reports.
    print("| check | what | value | ratio |\n|---|---|---|---|", flush=True)
    if "cudagraphs" in args.sections:
        from torch._dynamo.utils import counters

        skips = [str(w.message) for w in caught if issubclass(w.category, CUDAGraphSkipWarning)]
        emit([f"| cudagraphs | skipped graphs (Inductor's count) | {counters['inductor']['cudagraph_skips']} | |"])
        emit([f"| cudagraphs | warning | {' '.join(message.split())[:300]} | |" for message in skips])
    report = [step for step in (1, 40, 100) if step <= args.equality_steps]
    if "draws" in args.sections:
        modes: list[Any] = [True, "reduce-overhead"] if cuda else [True]
        for mode in modes:
            emit([f"| draws | compile_update={mode!r} | {compiled_vs_eager.draw_account(args.device, mode)} | |"])
        for aggregation in args.aggregations:
            account = compiled_vs_eager.step_draws_account(aggregation, args.device, args.policy_kwargs)
            emit([f"| draws | {aggregation} | {account} | |"])
    compared = {
        "equality": ("compiled", ""),
        "order": ("compiled-unordered", ", draws in Inductor's order"),
        "draws": ("compiled-fixed-draws", ", the normal draws fixed"),
    }
    for section, (against, how) in compared.items():
        if section not in args.sections:
            continue
        for aggregation in args.aggregations:
            differences = compiled_vs_eager.differences(
                aggregation, against, args.equality_steps, report, args.device, policy_kwargs=args.policy_kwargs
            )
            cells = ", ".join(f"after {step}: {value:.1e} ({name})" for step, (value, name) in differences.items())
            emit([f"| compiled vs eager | {aggregation}{how} | {cells} | |"])
    if "gradients" in args.sections:
        for aggregation in args.aggregations:
            account = compiled_vs_eager.gradient_differences(aggregation, args.gradient_steps, args.device, args.policy_kwargs)
            emit([f"| compiled vs eager gradients | {aggregation} | {account} | |"])
    if "speed" in args.sections:
        emit(speed_rows(single, "SB3 SAC eager", args))
        emit(speed_rows(multi, "SERASAC-MA eager", args))
    if "split" in args.sections:
        compiled = "SERASAC reduce-overhead" if cuda else "SERASAC compile_update=True"
        emit(split_rows({name: single[name] for name in ("SB3 SAC eager", compiled)}, args.split_steps, cuda))
    if "many" in args.sections:
        emit(many_rows(args.env, common, args.processes, args.many_steps, cuda))
    if "floor" in args.sections:
        constructors = host_floor.floor_models("Pendulum-v1", args.ma_env, args.device)
        floor = {name: host_floor.build(constructor) for name, constructor in constructors.items()}
        emit(["", *host_floor.floor_table(floor, args.blocks, args.block_steps)])
        emit(["", *host_floor.step_call_rows(host_floor.compiled_models(floor), args.split_steps)])
    seconds = time.perf_counter() - started
    device = f"{th.cuda.get_device_name()}, CUDA {th.version.cuda}" if cuda else "CPU"
    print(f"\n{device}, torch {th.__version__}; {seconds:.0f} s", flush=True)


if __name__ == "__main__":
    main()
