"""IET's search space for rl-zoo3's ``optimize``: SAC's (its network size for the critics), plus the latent size."""

from typing import Any

from sb3_sera.common.tuning import TuningSpace, convert_off_policy, sample_sac_space


def sample_iet_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """rl-zoo3's SAC search space (its network size for the critics) plus IET's latent size."""
    hyperparams = sample_sac_space(trial, n_actions, n_envs, additional_args)
    hyperparams["latent_dim"] = trial.suggest_categorical("latent_dim", [5, 10, 16])
    return hyperparams


IET_TUNING = TuningSpace(sample_iet_params, convert_off_policy)
