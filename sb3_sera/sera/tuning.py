"""SERASAC's search space for rl-zoo3's ``optimize``: SAC's, with the network size for the actor only, and SERA's knobs."""

from typing import Any

from sb3_sera.common.tuning import TuningSpace, convert_off_policy, sample_sac_space


def _actor_only(hyperparams: dict[str, Any]) -> dict[str, Any]:
    """Apply the zoo's network size to the actor only: SERASAC's critics keep the Table 4 architectures."""
    policy_kwargs = hyperparams.setdefault("policy_kwargs", {})
    if isinstance(policy_kwargs.get("net_arch"), list):
        policy_kwargs["net_arch"] = {"pi": policy_kwargs["net_arch"]}
    return hyperparams


def sample_serasac_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """rl-zoo3's SAC search space (network size for the actor only) plus SERA's own knobs."""
    hyperparams = _actor_only(sample_sac_space(trial, n_actions, n_envs, additional_args))
    hyperparams.update(
        sera_alpha=trial.suggest_float("sera_alpha", 0.0, 1.0),
        sera_temperature=trial.suggest_float("sera_temperature", 0.1, 10.0, log=True),
        critic_lr_max=trial.suggest_float("critic_lr_max", 1e-4, 2e-3, log=True),
        disagreement_coef=trial.suggest_float("disagreement_coef", 0.0, 0.1),
    )
    return hyperparams


def convert_serasac_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """A stored trial's parameters as SERASAC's: rl-zoo3's off-policy conversion, network size for the actor only."""
    return _actor_only(convert_off_policy(sampled_params))


SERASAC_TUNING = TuningSpace(sample_serasac_params, convert_serasac_params)
