"""
Hyperparameter search spaces for rl-zoo3's ``optimize``: an algorithm with a space of its own declares it on its
class as ``tuning`` (a :class:`TuningSpace`), one tuned in an SB3 algorithm's space names that algorithm in
``tunes_like`` (:class:`~sb3_sera.common.capabilities.Capabilities`). rl-zoo3 is imported only when a space is used:
it is the library's ``zoo`` extra (``pip install "sb3-sera[zoo]"``).
"""

from collections.abc import Callable
from typing import Any, NamedTuple

from sb3_sera.common.extras import needs_zoo_extra

#: rl-zoo3's sampler signature: ``(trial, n_actions, n_envs, additional_args) -> hyperparameters``
Sampler = Callable[[Any, int, int, dict], dict[str, Any]]


class TuningSpace(NamedTuple):
    """An algorithm's entries in rl-zoo3's ``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER`` tables."""

    #: draws one trial's hyperparameters from an Optuna trial
    sample: Sampler
    #: turns a stored trial's flat parameters back into hyperparameters (``policy_kwargs`` nested again)
    convert: Callable[[dict[str, Any]], dict[str, Any]]


def sample_sac_space(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """rl-zoo3's SAC search space (``rl_zoo3.hyperparams_opt.sample_sac_params``)."""
    with needs_zoo_extra("The -optimize search space sb3_sera.common.tuning.sample_sac_space()"):
        from rl_zoo3.hyperparams_opt import sample_sac_params

    return sample_sac_params(trial, n_actions=n_actions, n_envs=n_envs, additional_args=additional_args)


def convert_off_policy(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """rl-zoo3's conversion of an off-policy trial's parameters (``convert_offpolicy_params``)."""
    with needs_zoo_extra("The -optimize search space sb3_sera.common.tuning.convert_off_policy()"):
        from rl_zoo3.hyperparams_opt import convert_offpolicy_params

    return convert_offpolicy_params(sampled_params)
