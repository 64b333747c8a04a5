"""SUNRISE's search space for rl-zoo3's ``optimize``: SAC's, plus the ensemble size, backup temperature and UCB."""

from typing import Any

from sb3_sera.common.tuning import TuningSpace, convert_off_policy, sample_sac_space


def sample_sunrise_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """rl-zoo3's SAC search space plus SUNRISE's ensemble size N, backup temperature T and UCB lambda."""
    hyperparams = sample_sac_space(trial, n_actions, n_envs, additional_args)
    hyperparams.update(
        n_members=trial.suggest_int("n_members", 2, 10),
        backup_temperature=trial.suggest_float("backup_temperature", 1.0, 50.0, log=True),
        ucb_lambda=trial.suggest_categorical("ucb_lambda", [0.0, 1.0, 10.0]),
    )
    return hyperparams


SUNRISE_TUNING = TuningSpace(sample_sunrise_params, convert_off_policy)
