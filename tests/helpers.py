"""What several test files share: the repository's root, the small tasks and settings models are trained with,
comparisons of a model's torch state, and the command line run as a terminal runs it (Ctrl-C included)."""

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th

#: The repository's top folder (README, docs, notebooks, benchmarks, results, hyperparams)
ROOT = Path(__file__).resolve().parents[1]
#: The single-agent task most tests train on
ENV_ID = "Pendulum-v1"
#: The multi-agent (CTDE) task most tests train on
CTDE_TASK = "sb3_sera/SimpleSpread-v0"
#: Off-policy settings small enough for a test on ``ENV_ID``: training starts after 50 steps, a small buffer
SMALL = dict(learning_starts=50, batch_size=32, buffer_size=2_000)
#: The same on ``CTDE_TASK``, with a smaller buffer
SMALL_CTDE = dict(learning_starts=50, batch_size=32, buffer_size=1_000)


def snapshot(model: Any, optimizers: bool = False) -> dict[str, th.Tensor]:
    """
    A copy of what a SAC- or TD3-style model learns: its policy's state (actor, critics, targets), its step-size state
    where it has one (SERASAC) and its entropy coefficient where it learns one; with ``optimizers``, the state of its
    actor, critic and entropy coefficient optimizers too (Adam's moments and step counts).
    """
    state = {f"policy.{k}": v.clone() for k, v in model.policy.state_dict().items()}
    if getattr(model, "step_size", None) is not None:
        state.update({f"step_size.{k}": v.clone() for k, v in model.step_size.state_dict().items()})
    if getattr(model, "log_ent_coef", None) is not None:
        state["log_ent_coef"] = model.log_ent_coef.detach().clone()
    if optimizers:
        named = {
            "actor": model.actor.optimizer,
            "critic": model.critic.optimizer,
            "ent_coef": getattr(model, "ent_coef_optimizer", None),
        }
        for name, optimizer in named.items():
            for index, param_state in ({} if optimizer is None else optimizer.state_dict()["state"]).items():
                state.update({f"{name}.{index}.{key}": value.clone() for key, value in param_state.items()})
    return state


def assert_same_state(first: dict[str, th.Tensor], second: dict[str, th.Tensor]) -> None:
    """The two snapshots hold the same tensors under the same names, bit for bit."""
    assert first.keys() == second.keys()
    for key in first:
        assert th.equal(first[key], second[key]), key


def assert_close_state(first: dict[str, th.Tensor], second: dict[str, th.Tensor]) -> None:
    """The two snapshots hold the same tensors under the same names up to float rounding (a compiled step's)."""
    assert first.keys() == second.keys()
    for key, value in first.items():
        np.testing.assert_allclose(value.float(), second[key].float(), rtol=1e-4, atol=1e-5, err_msg=key)


def assert_schedule_does_not_recompile(model: Any, batch_size: int, rate: Any) -> None:
    """
    Ten ``train()`` calls at falling progress make no new graph of ``model``'s compiled step, and the actor's optimizer
    follows ``rate(progress)``: the step reads no optimizer (Dynamo would guard on each group's ``lr``, a new graph at
    every call, and fail at the ninth).
    """
    from torch._dynamo.utils import counters

    graphs = counters["stats"]["unique_graphs"]
    for call in range(10):
        model._current_progress_remaining = 1 - call / 10
        model.train(gradient_steps=1, batch_size=batch_size)
        assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(rate(1 - call / 10))
    assert counters["stats"]["unique_graphs"] == graphs


def assert_non_finite_stops_the_step(model: Any, batch_size: int) -> None:
    """
    With NaN rewards in ``model``'s replay buffer, ``train()`` raises ``FloatingPointError`` naming the TD target and
    the first step, and no parameter or optimizer state changes (a compiled step's masked updates).
    """
    model.replay_buffer.rewards[:] = np.nan
    before, updates = snapshot(model, optimizers=True), model._n_updates
    with pytest.raises(FloatingPointError, match=rf"^Non-finite TD target at gradient step {updates + 1} "):
        model.train(gradient_steps=3, batch_size=batch_size)
    assert_same_state(before, snapshot(model, optimizers=True))


def serasac_as_sac(env: Any, optimizer_kwargs: dict[str, Any] | None = None) -> Any:
    """
    SERASAC configured as SB3's SAC (two ``[256, 256]`` critics, min target and actor, fixed critic rate, beta = 0):
    the same losses and updates as SAC; ``optimizer_kwargs`` (None: SERASAC's default, fused Adam).
    """
    from sb3_sera import SERASAC

    policy_kwargs: dict[str, Any] = dict(n_critics=2, net_arch=[256, 256])
    if optimizer_kwargs is not None:
        policy_kwargs["optimizer_kwargs"] = optimizer_kwargs
    return SERASAC(
        "MlpPolicy",
        env,
        seed=1,
        learning_starts=200,
        batch_size=64,
        target_aggregation="min",
        actor_aggregation="min",
        adaptive_critic_lr=False,
        disagreement_coef=0.0,
        policy_kwargs=policy_kwargs,
    )


def _default_sigint() -> None:
    # A job started in the background (`cmd &`, nohup) ignores SIGINT, and its children inherit that: Python then
    # raises no KeyboardInterrupt, and a Ctrl-C test would see a command that cannot be interrupted
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_command(*args: str, stderr: int = subprocess.PIPE) -> subprocess.Popen:
    """
    ``python -m sb3_sera <args>`` started as a terminal starts it: a process group of its own with SIGINT's default
    action (whatever the test runner's), one torch thread.
    """
    return subprocess.Popen(
        [sys.executable, "-m", "sb3_sera", *args],
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        start_new_session=True,
        preexec_fn=_default_sigint,
    )


@contextmanager
def killed_at_exit(process: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """``process`` for the block; its process group killed after it, should it still run (a test that failed)."""
    try:
        yield process
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)


def ctrl_c(process: subprocess.Popen, timeout: float) -> str:
    """What a terminal's Ctrl-C sends (SIGINT to the whole process group); ``process``'s standard error once it ends."""
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=timeout)
    return stderr
