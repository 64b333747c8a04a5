"""ACE's own search space for rl-zoo3's ``optimize``: optimizer and target settings, exploration, heads and tree."""

from typing import Any

from sb3_sera.common.tuning import TuningSpace


def sample_ace_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """ACE's own search space: the optimizer and target settings, the exploration noise, the heads and the tree."""
    return {
        "learning_rate": trial.suggest_float("learning_rate", 3e-5, 1e-3, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256]),
        "tau": trial.suggest_categorical("tau", [0.001, 0.005, 0.01]),
        "gamma": trial.suggest_categorical("gamma", [0.98, 0.99, 0.995]),
        "exploration_noise": trial.suggest_float("exploration_noise", 0.1, 0.5),
        "policy_kwargs": {"n_actors": trial.suggest_int("n_actors", 1, 8), "depth": trial.suggest_int("depth", 1, 3)},
    }


def convert_ace_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """ACE's stored trial as its hyperparameters: the heads and depth back into ``policy_kwargs``."""
    params = dict(sampled_params)
    params["policy_kwargs"] = {"n_actors": params.pop("n_actors"), "depth": params.pop("depth")}
    return params


ACE_TUNING = TuningSpace(sample_ace_params, convert_ace_params)
