"""
Every algorithm refuses a hyperparameter outside its range at construction, with a ``ValueError`` that names the
parameter, its value and the allowed range (one set of rules: ``sb3_sera.common.hyperparameters``).
"""

import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_sera import IET, MADDPG, MAPPO, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.ace import ACE
from sb3_sera.common.hyperparameters import base_arguments, check_hyperparameters
from tests.helpers import CTDE_TASK, ENV_ID

#: A buffer small enough for a test
SMALL_BUFFER = dict(buffer_size=1_000)


def build(name: str) -> Callable[..., BaseAlgorithm]:
    """``name``'s constructor on a small task, extra keyword arguments given to it."""
    return {
        "ACE": lambda **kwargs: ACE("MlpPolicy", ENV_ID, **{**SMALL_BUFFER, **kwargs}),
        "SUNRISE": lambda **kwargs: SUNRISE("MlpPolicy", ENV_ID, **{**SMALL_BUFFER, **kwargs}),
        "SERASAC": lambda **kwargs: SERASAC("CTDEPolicy", CTDE_TASK, **{**SMALL_BUFFER, **kwargs}),
        "MASAC": lambda **kwargs: MASAC("CTDEPolicy", CTDE_TASK, **{**SMALL_BUFFER, **kwargs}),
        "MATD3": lambda **kwargs: MATD3("CTDEPolicy", CTDE_TASK, **{**SMALL_BUFFER, **kwargs}),
        "MADDPG": lambda **kwargs: MADDPG("CTDEPolicy", CTDE_TASK, **{**SMALL_BUFFER, **kwargs}),
        "IET": lambda **kwargs: IET("CTDEPolicy", CTDE_TASK, **{**SMALL_BUFFER, **kwargs}),
        "MAPPO": lambda **kwargs: MAPPO("CTDEPolicy", CTDE_TASK, **kwargs),
    }[name]


OFF_POLICY = ["ACE", "SUNRISE", "SERASAC", "MASAC", "MATD3", "MADDPG", "IET"]
SAC_FAMILY = ["SERASAC", "MASAC", "IET", "SUNRISE"]
CTDE_OFF_POLICY = ["MASAC", "MATD3", "MADDPG", "IET"]
#: (hyperparameter, bad value, the allowed range as the message gives it), for each algorithm that has it
OFF_POLICY_CASES = [
    ("learning_rate", 0.0, r"\(0\.0, inf\)"),
    ("learning_rate", -1e-3, r"\(0\.0, inf\)"),
    ("buffer_size", 0, "an integer >= 1"),
    ("learning_starts", -1, "an integer >= 0"),
    ("batch_size", 0, "an integer >= 1"),
    ("batch_size", 2.5, "an integer >= 1"),
    ("tau", 1.5, r"\[0\.0, 1\.0\]"),
    ("tau", -0.1, r"\[0\.0, 1\.0\]"),
    ("gamma", 1.5, r"\[0\.0, 1\.0\]"),
    ("gamma", float("nan"), r"\[0\.0, 1\.0\]"),
    ("gradient_steps", -2, "an integer >= 0"),
]
CASES = [
    *[(name, *case) for name in OFF_POLICY for case in OFF_POLICY_CASES],
    *[(name, "train_freq", 0, "an integer >= 1") for name in OFF_POLICY],
    *[(name, "stats_window_size", 0, "an integer >= 1") for name in OFF_POLICY if name != "MADDPG"],
    *[(name, "n_steps", 0, "an integer >= 1") for name in ("ACE", "SERASAC", "MASAC", "MATD3", "MADDPG", "IET")],
    *[(name, "target_update_interval", 0, "an integer >= 1") for name in SAC_FAMILY],
    *[(name, "ent_coef", -0.1, r"\(0\.0, inf\)") for name in SAC_FAMILY],
    *[(name, "policy_kwargs", dict(n_critics=0), "an integer >= 1") for name in ("SUNRISE", *CTDE_OFF_POLICY)],
    ("SERASAC", "policy_kwargs", dict(n_critics=0), "an integer >= 2"),
    ("MATD3", "policy_delay", 0, "an integer >= 1"),
    ("MATD3", "target_policy_noise", -0.2, r"\[0\.0, inf\)"),
    ("MATD3", "target_noise_clip", -0.5, r"\[0\.0, inf\)"),
    ("ACE", "policy_kwargs", dict(depth=0), "an integer >= 1"),
    ("ACE", "policy_kwargs", dict(feature_dim=0), "an integer >= 1"),
    ("ACE", "exploration_noise", -0.3, r"\[0\.0, inf\)"),
    ("ACE", "align_next_value", "yes", "one of True, False"),
    ("IET", "latent_dim", 0, "an integer >= 1"),
    ("MAPPO", "learning_rate", 0.0, r"\(0\.0, inf\)"),
    ("MAPPO", "n_steps", 0, "an integer >= 1"),
    ("MAPPO", "batch_size", 1, "an integer >= 2"),
    ("MAPPO", "n_epochs", 0, "an integer >= 1"),
    ("MAPPO", "gamma", 1.5, r"\[0\.0, 1\.0\]"),
    ("MAPPO", "gae_lambda", -0.5, r"\[0\.0, 1\.0\]"),
    ("MAPPO", "clip_range", 0.0, r"\(0\.0, inf\)"),
    ("MAPPO", "clip_range_vf", -0.2, r"\(0\.0, inf\)"),
    ("MAPPO", "ent_coef", -0.01, r"\[0\.0, inf\)"),
    ("MAPPO", "vf_coef", -0.5, r"\[0\.0, inf\)"),
    ("MAPPO", "max_grad_norm", 0.0, r"\(0\.0, inf\)"),
    ("MAPPO", "target_kl", 0.0, r"\(0\.0, inf\)"),
]


def bad_name_and_value(parameter: str, value: Any) -> tuple[str, Any]:
    """The name and value the message gives: a policy kwarg's own name for ``policy_kwargs``."""
    return next(iter(value.items())) if isinstance(value, dict) else (parameter, value)


@pytest.mark.parametrize(
    ("algo", "parameter", "value", "allowed"),
    CASES,
    ids=[f"{algo}-{parameter}={value}" for algo, parameter, value, _ in CASES],
)
def test_a_value_out_of_range_is_refused_at_construction(algo, parameter, value, allowed):
    name, bad = bad_name_and_value(parameter, value)
    message = rf"^{name}={re.escape(repr(bad))} is (out of range: allowed|invalid: expected) (a finite number in )?{allowed}"
    with pytest.raises(ValueError, match=message):
        build(algo)(**{parameter: value})


@pytest.mark.parametrize("algo", [MASAC, MATD3, MADDPG])
def test_positional_hyperparameters_are_checked_too(algo):
    with pytest.raises(ValueError, match=r"^learning_rate=0\.0 is out of range"):
        algo("CTDEPolicy", CTDE_TASK, 0.0)
    with pytest.raises(ValueError, match=r"^tau=1\.5 is out of range"):
        algo("CTDEPolicy", CTDE_TASK, 1e-3, 1_000, 100, 32, 1.5)


@pytest.mark.parametrize("name", ["ACE", "SUNRISE", "SERASAC", "MASAC", "MATD3", "MADDPG", "IET"])
def test_numbers_as_yaml_and_numpy_give_them_as_python_numbers(name):
    model = build(name)(learning_starts=1e2, batch_size=np.int64(16), tau=np.float32(0.5), gamma=np.float64(0.9))
    assert (model.learning_starts, model.batch_size, model.tau, model.gamma) == (100, 16, 0.5, 0.9)
    assert type(model.learning_starts) is int and type(model.tau) is float


def test_base_arguments_pass_on_what_the_base_takes_checked_and_the_algorithms_own_values():
    def base_init(self, policy, env, learning_rate=3e-4, batch_size=256, supported_action_spaces=None):
        """An SB3 constructor's shape."""

    arguments = dict(self=None, policy="MlpPolicy", env="E", learning_rate=np.float32(0.5), batch_size=1e2, n_members=5)
    passed = base_arguments(base_init, arguments, supported_action_spaces=("Box",))
    assert passed == dict(policy="MlpPolicy", env="E", learning_rate=0.5, batch_size=100, supported_action_spaces=("Box",))
    assert type(passed["batch_size"]) is int and type(passed["learning_rate"]) is float
    with pytest.raises(ValueError, match=r"^batch_size=0 is "):
        base_arguments(base_init, {**arguments, "batch_size": 0})


def test_every_rule_names_its_parameter():
    # Names without a rule pass as they are; schedules pass where SB3 takes them
    schedule = lambda progress: 1e-3 * progress  # noqa: E731
    assert check_hyperparameters({"seed": 3, "learning_rate": schedule, "device": "cpu"}) == {
        "seed": 3,
        "learning_rate": schedule,
        "device": "cpu",
    }
    assert check_hyperparameters({"clip_range": schedule, "target_kl": None}, on_policy=True) == {
        "clip_range": schedule,
        "target_kl": None,
    }
    assert check_hyperparameters({"gradient_steps": -1, "train_freq": (2, "episode")}) == {
        "gradient_steps": -1,
        "train_freq": (2, "episode"),
    }
    with pytest.raises(ValueError, match=r"^train_freq=\(1, 'epoch'\) is invalid"):
        check_hyperparameters({"train_freq": (1, "epoch")})


@pytest.mark.parametrize("value", ["x", float("nan"), None])
def test_target_entropy_is_auto_or_a_finite_number(value):
    with pytest.raises(ValueError, match=r"target_entropy=.* is invalid: expected 'auto' \(minus the action size\)"):
        SERASAC("MlpPolicy", ENV_ID, target_entropy=value, **SMALL_BUFFER)
    assert SERASAC("MlpPolicy", ENV_ID, target_entropy=-2, **SMALL_BUFFER).target_entropy == -2.0
