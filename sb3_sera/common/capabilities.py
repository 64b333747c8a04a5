"""What an algorithm of the package supports, declared on its class (BenchMARL's way) instead of lists kept elsewhere."""

from typing import Any, ClassVar, Protocol, cast

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecEnv

from sb3_sera.common.tuning import TuningSpace


class Capabilities:
    """
    Class attributes every algorithm of the package sets: the zoo bridge, the run engine and the playback commands
    read them, so that adding an algorithm means declaring them on its class.
    """

    #: Trains on single-agent Gymnasium tasks
    single_agent: ClassVar[bool] = True
    #: Trains on the multi-agent CTDE tasks (``"CTDEPolicy"``)
    multi_agent: ClassVar[bool] = True
    #: Learns from a replay buffer (rl-zoo3's playback loads such a model with a one-transition buffer)
    off_policy: ClassVar[bool] = True
    #: Has Q critics ``critic(obs, action)`` (the evaluations record the initial-state bias and critic diagnostics)
    has_q_critics: ClassVar[bool] = True
    #: The SB3 algorithm (rl-zoo3's name) whose hyperparameter sampler tunes it; None: a sampler of its own
    tunes_like: ClassVar[str | None] = None
    #: SAC's soft Q critics over a replay buffer (``actor``, ``critic``, ``critic_target``): the evaluations record
    #: their critic diagnostics
    soft_q_critics: ClassVar[bool] = False
    #: Its critics regress on a TD target of its own, given by ``td_targets(replay_data)`` (not SAC's twin minimum)
    own_td_targets: ClassVar[bool] = False
    #: Learns a rate per critic, given by ``critic_learning_rates()``
    per_critic_rates: ClassVar[bool] = False
    #: Acts on per-episode latents that an env gets from ``with_latents(env, seed)`` (evaluation envs included)
    acts_on_latents: ClassVar[bool] = False
    #: Its own search space for rl-zoo3's ``optimize`` (:class:`~sb3_sera.common.tuning.TuningSpace`), declared
    #: beside the algorithm; None: it tunes like ``tunes_like``
    tuning: ClassVar[TuningSpace | None] = None


class OwnTDTargets(Protocol):
    """What a model with ``own_td_targets`` has."""

    def td_targets(self, replay_data: ReplayBufferSamples) -> tuple[th.Tensor, th.Tensor]:
        """The TD target of a replayed batch and the online critics' values, ``(S, 1)`` and ``(S, K)``."""


class PerCriticRates(Protocol):
    """What a model with ``per_critic_rates`` has."""

    def critic_learning_rates(self) -> list[float]:
        """Each critic's current learning rate."""


class ActsOnLatents(Protocol):
    """What a model with ``acts_on_latents`` has."""

    def with_latents(self, env: VecEnv, seed: int | None = None) -> VecEnv:
        """``env`` with the model's latents added to its observations."""


def capabilities(algorithm: type[Any]) -> dict[str, Any]:
    """
    The capabilities an algorithm class declares (every attribute of :class:`Capabilities`); for one of SB3's own
    (rl-zoo3's baselines), which declares none, the defaults, SAC's family with its soft Q critics.
    """
    from stable_baselines3 import SAC

    names = [name for name in vars(Capabilities) if not name.startswith("_")]
    if issubclass(algorithm, Capabilities):
        return {name: getattr(algorithm, name) for name in names}
    return {name: getattr(Capabilities, name) for name in names} | {"soft_q_critics": issubclass(algorithm, SAC)}


def capability(model: Any, name: str) -> Any:
    """The capability ``name`` of ``model``'s class (:func:`capabilities`)."""
    return capabilities(type(model))[name]


def as_the_model_sees(model: Any, env: VecEnv) -> VecEnv:
    """
    ``env`` as ``model`` acts in it: with the model's latents added (``with_latents``, seeded with the model's seed as
    the evaluation callback seeds them) for a model acting on latents, else ``env`` itself.
    """
    if capability(model, "acts_on_latents"):
        return cast(ActsOnLatents, model).with_latents(env, seed=model.seed)
    return env
