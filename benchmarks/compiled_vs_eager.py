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
no ``torch.compile``); ``--against compiled-unordered`` with the step compiled without chaining its random draws
(:func:`unordered_draws`: whether Inductor's scheduler alone keeps their order); ``--against compiled-fixed-draws``
with both models' normal draws (how the actors sample) replaced by the same fixed numbers (:func:`fixed_draws`): what
differs then is not the draws.
"""

import argparse
import ast
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
from sb3_sera.common.compiled import base as compiled_base
from sb3_sera.common.compiled import graph_passes
from sb3_sera.common.compiled.modes import CompileMode, compile_step
from sb3_sera.sera import sera as sera_module
from sb3_sera.sera.update import actor_value_gathered

BATCH_SIZE, FILL = 32, 64
AGAINST = ("compiled", "compiled-unordered", "compiled-fixed-draws", "eager-gathered", "step-uncompiled")


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


def train_in_step(
    models: list[SERASAC],
    steps: int,
    on_step: Callable[[int], None],
    after_each: Callable[[SERASAC], None] = lambda model: None,
) -> None:
    """
    One gradient step per ``train()`` call for each model, on the same batch and random draws: numpy's generator
    (the replay buffer's sampling), torch's CPU generator and, for models on a GPU, that device's generator, each set
    back to the same state before every model's step; ``after_each`` called with each model after its step.
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
            after_each(model)
        on_step(step)


def gathered(train: Callable[..., None]) -> Callable[..., None]:
    """``train`` with the eager actor value taken as the compiled step takes it (:func:`actor_value_gathered`)."""

    def run(*args: Any, **kwargs: Any) -> None:
        with mock.patch.object(sera_module, "actor_value", actor_value_gathered):
            train(*args, **kwargs)

    return run


def differences(
    aggregation: str,
    against: str,
    steps: int,
    report: list[int],
    device: str = "cpu",
    bound: float = math.inf,
    policy_kwargs: dict[str, Any] | None = None,
) -> dict[int, tuple[float, str]]:
    """
    The largest parameter difference between eager SERASAC and ``against`` (and the tensor where it is) after each
    step of ``report``; with a finite ``bound``, also under the key 0 the first step past it and its difference.
    Both models are built with ``policy_kwargs`` (SERASAC's defaults where None).
    """
    settings: dict[str, Any] = dict(actor_aggregation=aggregation, device=device, policy_kwargs=policy_kwargs)
    eager = make_model(False, **settings)
    if against == "step-uncompiled":
        with mock.patch.object(compiled_base, "compile_step", lambda step, mode: step):
            other = make_model(True, **settings)
    else:
        other = make_model(against.startswith("compiled"), **settings)
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
    drawing = {"compiled-unordered": unordered_draws, "compiled-fixed-draws": fixed_draws}
    with drawing.get(against, contextlib.nullcontext)():
        train_in_step([eager, other], steps, on_step)
    return found


def _optimized(model: SERASAC) -> dict[str, tuple[th.Tensor, dict[str, Any]]]:
    """Every tensor the model's optimizers step, by name, with its Adam state."""
    names = {id(param): name for name, param in model.policy.named_parameters()}
    assert model.log_ent_coef is not None and model.ent_coef_optimizer is not None
    names[id(model.log_ent_coef)] = "log_ent_coef"
    optimizers = [model.actor.optimizer, model.critic.optimizer, model.ent_coef_optimizer]
    return {
        names[id(param)]: (param, optimizer.state[param])
        for optimizer in optimizers
        for group in optimizer.param_groups
        for param in group["params"]
    }


def _copy_state(source: SERASAC, target: SERASAC) -> None:
    """``target``'s parameters, targets, step-size statistics and Adam states set to ``source``'s, in place."""
    with th.no_grad():
        for module in ("policy", "step_size"):
            for name, value in getattr(source, module).state_dict().items():
                getattr(target, module).state_dict()[name].copy_(value)
        assert source.log_ent_coef is not None and target.log_ent_coef is not None
        target.log_ent_coef.copy_(source.log_ent_coef)
        theirs = _optimized(target)
        for name, (_, state) in _optimized(source).items():
            for key, value in state.items():
                theirs[name][1][key].copy_(value)


def _first_moments(model: SERASAC) -> dict[str, th.Tensor]:
    # Before the first step Adam has no state (a tensor without one is left out: its moment is zero)
    return {name: state["exp_avg"].detach().clone() for name, (_, state) in _optimized(model).items() if state}


def _gradients(model: SERASAC, before: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    """The last step's gradients, from Adam's first moments before and after it: ``(m - beta1 m_before) / (1 - beta1)``."""
    beta1 = model.actor.optimizer.param_groups[0]["betas"][0]
    moments = _first_moments(model)
    # Before the first step Adam has no state: its moments start at zero
    return {name: (moment - beta1 * before.get(name, 0.0)) / (1 - beta1) for name, moment in moments.items()}


def gradient_differences(
    aggregation: str, steps: int, device: str = "cpu", policy_kwargs: dict[str, Any] | None = None
) -> str:
    """
    Eager and compiled SERASAC's gradients (both built with ``policy_kwargs``), each step from the same state (the
    compiled model's set to the eager one's before it, in place) on the same batch and draws; the gradients read from
    Adam's first moments. Returns the account: the largest difference over ``steps`` steps relative to each tensor's
    largest eager gradient, and, after the first step, the parameter elements that part by more than 1e-6, with their
    eager gradients against Adam's ``eps`` and float32 rounding.
    """
    settings: dict[str, Any] = dict(actor_aggregation=aggregation, device=device, policy_kwargs=policy_kwargs)
    eager = make_model(False, **settings)
    compiled = make_model(True, **settings)
    largest, account = 0.0, ""
    for step in range(1, steps + 1):
        _copy_state(eager, compiled)
        before = _first_moments(eager)
        train_in_step([eager, compiled], 1, lambda step: None)
        mine, theirs = _gradients(eager, before), _gradients(compiled, before)
        for name, gradient in mine.items():
            scale = gradient.abs().max().clamp_min(th.finfo(gradient.dtype).tiny)
            largest = max(largest, float(((theirs[name] - gradient).abs().max() / scale).item()))
        if step == 1:
            account = _first_step_account(eager, compiled, mine, theirs)
    return f"largest gradient difference over {steps} steps {largest:.1e} of the tensor's largest gradient; {account}"


def _first_step_account(eager: SERASAC, compiled: SERASAC, mine: dict[str, th.Tensor], theirs: dict[str, th.Tensor]) -> str:
    """The parameter elements that part by more than 1e-6 after one step, and their eager gradients."""
    epsilon = th.finfo(th.float32).eps
    parted, gradients, flipped, at_rounding = 0, [], 0, 0
    others = _optimized(compiled)
    for name, (param, _) in _optimized(eager).items():
        other = others[name][0]
        where = (param.detach() - other.detach()).abs() > 1e-6
        if not where.any():
            continue
        parted += int(where.sum().item())
        gradient, difference = mine[name][where].abs(), (theirs[name] - mine[name])[where].abs()
        gradients.append(float(gradient.max().item()))
        flipped += int((difference >= gradient).sum().item())
        # Rounding's scale: float32's epsilon times the tensor's largest gradient, times the batch's terms
        at_rounding += int((gradient <= epsilon * mine[name].abs().max() * BATCH_SIZE).sum().item())
    if parted == 0:
        return "after one step no parameter element parts by more than 1e-6"
    return (
        f"after one step {parted} parameter element(s) part by more than 1e-6: their eager |gradient| at most "
        f"{max(gradients):.1e} (Adam's eps 1e-8), {at_rounding} within float32 rounding of their tensor's largest "
        f"gradient (x batch {BATCH_SIZE}), {flipped} with the compiled gradient as far from the eager one as it is "
        "from zero (a sign rounding can flip)"
    )


@contextlib.contextmanager
def unordered_draws() -> Iterator[None]:
    """
    Steps compiled in it leave their random draws in the order Inductor's scheduler gives them: neither this
    package's :class:`~sb3_sera.common.compiled.graph_passes.KeepRandomOrder` nor torch's own chain (from torch 2.13) keeps
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


@contextlib.contextmanager
def fixed_draws() -> Iterator[None]:
    """
    In it every normal draw of ``torch.distributions.Normal.rsample`` (how SB3's squashed Gaussian actors sample),
    eager or compiled, is the same fixed spread of numbers instead of the generator's; no compiled graph is taken from
    this process's Dynamo cache.
    """

    def standard_normal(shape: tuple[int, ...], dtype: th.dtype | None, device: th.device | None) -> th.Tensor:
        spread = th.arange(math.prod(shape), dtype=dtype, device=device).mul(1.7).add(0.3).sin().mul(1.5)
        return spread.reshape(shape)

    th._dynamo.reset()
    with mock.patch.object(th.distributions.normal, "_standard_normal", standard_normal):
        yield


def _generator_state(device: str) -> th.Tensor:
    return th.cuda.get_rng_state(device) if device.startswith("cuda") else th.get_rng_state()


def _set_generator_state(device: str, state: th.Tensor) -> None:
    if device.startswith("cuda"):
        th.cuda.set_rng_state(state, device)
    else:
        th.set_rng_state(state)


def _actor_draws(loc: th.Tensor, scale: th.Tensor) -> tuple[th.Tensor, ...]:
    normal = th.distributions.Normal(loc, scale)
    return normal.rsample(), normal.rsample()


def _randn_draws(loc: th.Tensor, scale: th.Tensor) -> tuple[th.Tensor, ...]:
    return th.randn(loc.shape, device=loc.device) * scale + loc, th.randn(loc.shape, device=loc.device)


def _normal_draws(loc: th.Tensor, scale: th.Tensor) -> tuple[th.Tensor, ...]:
    return th.empty_like(loc).normal_(), th.empty_like(loc).normal_() * scale


#: The draws :func:`draw_account` compares: as an actor draws (``Normal.rsample``), ``randn``, in-place ``normal_``
DRAWS: dict[str, Callable[[th.Tensor, th.Tensor], tuple[th.Tensor, ...]]] = {
    "Normal.rsample": _actor_draws,
    "randn": _randn_draws,
    "normal_": _normal_draws,
}


def draw_account(device: str, mode: CompileMode) -> str:
    """
    Each of :data:`DRAWS` (two draws of a batch of two-dimensional actions), eager and compiled with ``mode`` (the
    gradient step's options), from the same state of ``device``'s generator, after three compiled calls (compilation,
    CUDA graph recording): the draws' largest difference, whether the compiled draws are eager's in the other order,
    and whether the generator ends in the same state.
    """
    loc = th.zeros(BATCH_SIZE, 2, device=device)
    scale = th.full_like(loc, 0.5)
    accounts = []
    for name, draw in DRAWS.items():
        th._dynamo.reset()
        compiled = compile_step(draw, mode)
        for _ in range(3):
            compiled(loc, scale)
        state = _generator_state(device)
        eager = draw(loc, scale)
        after_eager = _generator_state(device)
        _set_generator_state(device, state)
        theirs = [tensor.clone() for tensor in compiled(loc, scale)]
        same_end = th.equal(after_eager, _generator_state(device))
        largest = max((mine - other).abs().max().item() for mine, other in zip(eager, theirs, strict=True))
        swapped = th.equal(eager[0], theirs[1]) and th.equal(eager[1], theirs[0])
        accounts.append(
            f"{name}: {largest:.1e}{' (eager in the other order)' if swapped else ''}, generator after "
            f"{'the same' if same_end else 'another'} state"
        )
    return "; ".join(accounts)


def swapped_draws(train: Callable[..., None]) -> Callable[..., None]:
    """
    ``train`` (one gradient step a call) with its two normal draws (the actions at the observations, then at the next
    observations) taken from the generator in the other order: both drawn at the first, the second given first.
    """

    def run(*args: Any, **kwargs: Any) -> None:
        pending: list[th.Tensor] = []
        draw = th.distributions.normal._standard_normal

        def standard_normal(shape: tuple[int, ...], dtype: th.dtype | None, device: th.device | None) -> th.Tensor:
            if pending:
                return pending.pop()
            pending.append(draw(shape, dtype, device))
            return draw(shape, dtype, device)

        with mock.patch.object(th.distributions.normal, "_standard_normal", standard_normal):
            train(*args, **kwargs)

    return run


def step_draws_account(aggregation: str, device: str, policy_kwargs: dict[str, Any] | None = None) -> str:
    """
    One gradient step of eager, eager with its two draws swapped (:func:`swapped_draws`) and compiled SERASAC from the
    same state (after a first step of each, which compiles, the eager one's parameters, step-size statistics and Adam
    states copied into the others) on the same batch and generator states: each eager model's largest parameter
    difference to the compiled one, and whether each leaves the device's generator in the compiled step's state. The
    three are built with ``policy_kwargs``.
    """
    settings: dict[str, Any] = dict(actor_aggregation=aggregation, device=device, policy_kwargs=policy_kwargs)
    eager = make_model(False, **settings)
    swapped = make_model(False, **settings)
    swapped.train = swapped_draws(swapped.train)  # type: ignore[method-assign]
    compiled = make_model(True, **settings)
    models = {"eager": eager, "eager, draws swapped": swapped, "compiled": compiled}
    train_in_step(list(models.values()), 1, lambda step: None)
    _copy_state(eager, swapped)
    _copy_state(eager, compiled)
    after: dict[int, th.Tensor] = {}

    def record_generator(model: SERASAC) -> None:
        after[id(model)] = _generator_state(device)

    train_in_step(list(models.values()), 1, lambda step: None, record_generator)
    accounts = []
    for name in ("eager", "eager, draws swapped"):
        difference, where = largest_difference(models[name], compiled)
        same = "the same" if th.equal(after[id(models[name])], after[id(compiled)]) else "another"
        accounts.append(f"{name} {difference:.1e} ({where}), generator after {same} state")
    return "one step from the same state, against compiled: " + "; ".join(accounts)


def compare(
    aggregation: str,
    against: str,
    steps: int,
    bound: float,
    report: list[int],
    device: str,
    policy_kwargs: dict[str, Any] | None = None,
) -> None:
    found = differences(aggregation, against, steps, report, device, bound, policy_kwargs)
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
    parser.add_argument("--policy-kwargs", type=ast.literal_eval, help="SERASAC's policy_kwargs, a Python dict literal")
    args = parser.parse_args()
    th.set_num_threads(1)
    report = [step for step in (1, 12, 16, 24, 40, 100, 200) if step <= args.steps]
    print(f"eager against {args.against}: largest parameter difference after step ...")
    print(f"| actor aggregation | {' | '.join(str(step) for step in report)} | first above {args.bound:g} |")
    print(f"|---|{'---|' * len(report)}---|")
    for aggregation in args.aggregations:
        compare(aggregation, args.against, args.steps, args.bound, report, args.device, args.policy_kwargs)


if __name__ == "__main__":
    main()
