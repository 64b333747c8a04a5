"""
Compiled against eager: two SERASAC models, one with ``compile_update=True``, trained on the same fixed replay buffer
(Pendulum-v1, 64 random transitions), the same batches and the same random draws (every generator of the models'
device reset before each step: numpy's, torch's CPU one and, on a GPU, the device's), one gradient step per
``train()`` call. Prints, per actor aggregation, the largest parameter difference after each of the chosen steps,
and the first step at which it passes ``--bound`` with the parameter where it does.

    OMP_NUM_THREADS=1 python benchmarks/compiled_vs_eager.py --steps 100
    python benchmarks/compiled_vs_eager.py --device cuda --steps 100
    OMP_NUM_THREADS=1 python benchmarks/compiled_vs_eager.py --against eager-gathered   # no compilation

``--against eager-gathered`` compares the eager path with itself, its actor value taken as the compiled step takes
it (every critic with a graph, the selected one gathered, where the eager path runs the selected critic alone);
``--against step-uncompiled`` with the compiled path's step function run eagerly (its masked Adam and target update,
no ``torch.compile``); ``--against compiled-unordered`` with the step compiled without keeping its random
draws in program order (:func:`unordered_draws`: how a step compiled before ``KeepRandomOrder``, with a torch before
2.13, drew on CUDA).
"""

import argparse
import contextlib
import math
from collections.abc import Callable, Iterator
from typing import Any
from unittest import mock

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

from sb3_sera import SERASAC
from sb3_sera.common import graph_passes
from sb3_sera.common.compiled import base as compiled_base
from sb3_sera.sera import sera as sera_module
from sb3_sera.sera.update import actor_value_gathered

BATCH_SIZE, FILL = 32, 64
AGAINST = ("compiled", "compiled-unordered", "eager-gathered", "step-uncompiled")


def make_model(compile_update: bool, seed: int = 0, device: str = "cpu", **kwargs: Any) -> SERASAC:
    """A SERASAC model on Pendulum-v1 on ``device`` with a replay buffer of ``FILL`` seeded random transitions."""
    model = SERASAC(
        "MlpPolicy",
        gym.make("Pendulum-v1"),
        batch_size=BATCH_SIZE,
        seed=seed,
        compile_update=compile_update,
        device=device,
        **kwargs,
    )
    model.set_logger(configure(folder=None, format_strings=[]))
    assert model.replay_buffer is not None
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(FILL):
        action = env.action_space.sample()
        next_obs, reward, terminated, _, info = env.step(action)
        model.replay_buffer.add(obs[None], next_obs[None], action[None], np.array([reward]), np.array([terminated]), [info])
        obs = next_obs
    return model


def parameters(model: SERASAC) -> dict[str, th.Tensor]:
    """Every trained tensor of the model: the policy's (actor, critics, target critics) and the entropy coefficient."""
    tensors = {name: value.detach().clone() for name, value in model.policy.state_dict().items()}
    assert model.log_ent_coef is not None
    tensors["log_ent_coef"] = model.log_ent_coef.detach().clone()
    return tensors


def largest_difference(first: SERASAC, second: SERASAC) -> tuple[float, str]:
    """The largest absolute difference between the two models' tensors, and the tensor where it is."""
    a, b = parameters(first), parameters(second)
    differences = {name: (a[name].float() - b[name].float()).abs().max().item() for name in a}
    name = max(differences, key=lambda key: differences[key])
    return differences[name], name


def train_in_step(models: list[SERASAC], steps: int, on_step: Callable[[int], None]) -> None:
    """
    One gradient step per ``train()`` call for each model, on the same batch and random draws: numpy's generator
    (the replay buffer's sampling), torch's CPU generator and, for models on a GPU, that device's generator, each set
    back to the same state before every model's step.
    """
    devices = sorted({model.device for model in models if model.device.type == "cuda"}, key=str)
    for step in range(1, steps + 1):
        numpy_state, torch_state = np.random.get_state(), th.get_rng_state()
        device_states = [th.cuda.get_rng_state(device) for device in devices]
        for model in models:
            np.random.set_state(numpy_state)
            th.set_rng_state(torch_state)
            for device, state in zip(devices, device_states, strict=True):
                th.cuda.set_rng_state(state, device)
            model.train(gradient_steps=1, batch_size=BATCH_SIZE)
        on_step(step)


def gathered(train: Callable[..., None]) -> Callable[..., None]:
    """``train`` with the eager actor value taken as the compiled step takes it (:func:`actor_value_gathered`)."""

    def run(*args: Any, **kwargs: Any) -> None:
        with mock.patch.object(sera_module, "actor_value", actor_value_gathered):
            train(*args, **kwargs)

    return run


def differences(
    aggregation: str, against: str, steps: int, report: list[int], device: str = "cpu", bound: float = math.inf
) -> dict[int, tuple[float, str]]:
    """
    The largest parameter difference between eager SERASAC and ``against`` (and the tensor where it is) after each
    step of ``report``; with a finite ``bound``, also under the key 0 the first step past it and its difference.
    """
    eager = make_model(False, actor_aggregation=aggregation, device=device)
    if against == "step-uncompiled":
        with mock.patch.object(compiled_base, "compile_step", lambda step, mode: step):
            other = make_model(True, actor_aggregation=aggregation, device=device)
    else:
        other = make_model(against.startswith("compiled"), actor_aggregation=aggregation, device=device)
    if against == "eager-gathered":
        other.train = gathered(other.train)  # type: ignore[method-assign]
    found: dict[int, tuple[float, str]] = {}

    def on_step(step: int) -> None:
        difference, name = largest_difference(eager, other)
        if difference > bound and 0 not in found:
            found[0] = (float(step), name)
        if step in report:
            found[step] = (difference, name)

    # The step is compiled at its first train() call
    with unordered_draws() if against == "compiled-unordered" else contextlib.nullcontext():
        train_in_step([eager, other], steps, on_step)
    return found


@contextlib.contextmanager
def unordered_draws() -> Iterator[None]:
    """
    Steps compiled in it leave their random draws in the order Inductor's scheduler gives them: neither this
    package's :class:`~sb3_sera.common.graph_passes.KeepRandomOrder` nor torch's own chain (from torch 2.13) keeps
    them in program order, and no compiled graph is taken from this process's Dynamo cache or Inductor's caches.
    """
    from torch._inductor.fx_passes import post_grad

    th._dynamo.reset()
    with (
        mock.patch.object(graph_passes.KeepRandomOrder, "__call__", lambda self, graph: None),
        mock.patch.object(post_grad, "_chain_random_ops_for_ordering", lambda graph: None, create=True),
        th._inductor.config.patch(fx_graph_cache=False),
        th._functorch.config.patch(enable_autograd_cache=False),
    ):
        yield


def compare(aggregation: str, against: str, steps: int, bound: float, report: list[int], device: str) -> None:
    found = differences(aggregation, against, steps, report, device, bound)
    row = [f"{found[step][0]:.1e}" for step in report]
    passed = "never" if 0 not in found else f"step {found[0][0]:.0f} ({found[0][1]})"
    print(f"| {aggregation} | {' | '.join(row)} | {passed} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--against", choices=AGAINST, default="compiled")
    parser.add_argument("--aggregations", nargs="+", default=["median", "mean", "min"])
    parser.add_argument("--bound", type=float, default=2e-5)
    parser.add_argument("--device", default="cpu", help="the models' torch device, e.g. cuda")
    args = parser.parse_args()
    th.set_num_threads(1)
    report = [step for step in (1, 12, 16, 24, 40, 100, 200) if step <= args.steps]
    print(f"eager against {args.against}: largest parameter difference after step ...")
    print(f"| actor aggregation | {' | '.join(str(step) for step in report)} | first above {args.bound:g} |")
    print(f"|---|{'---|' * len(report)}---|")
    for aggregation in args.aggregations:
        compare(aggregation, args.against, args.steps, args.bound, report, args.device)


if __name__ == "__main__":
    main()
