"""
IET: Implicit Ensemble Training (Shen & How, TMLR 2023), adapted to cooperative CTDE tasks (docs/SPEC.md, section 4).

Our adaptation, not the authors' (their code is RLlib PPO on competitive games, with a "main/test" alternation
against adversaries that cooperative tasks do not have): MASAC whose per-agent actors are soft-modular networks
conditioned on a per-agent, per-episode Gaussian latent, with centralized critics that read the latents too.
Evaluation draws the latents the same way (one per agent per episode).
"""

import io
import pathlib
from collections.abc import Iterable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, unwrap_vec_normalize

from sb3_sera.common.arguments import checks_keywords, constructor_arguments
from sb3_sera.common.compiled import CompileMode
from sb3_sera.common.hyperparameters import check_int
from sb3_sera.common.tuning import TuningSpace
from sb3_sera.ctde.algorithms import MASAC
from sb3_sera.ctde.policies import agent_action_dims_of
from sb3_sera.iet.latents import LATENT_KEY, LatentVecEnv, draw_latents
from sb3_sera.iet.networks import routing_entropy
from sb3_sera.iet.policies import IETPolicy
from sb3_sera.iet.tuning import IET_TUNING

SelfIET = TypeVar("SelfIET", bound="IET")

#: The paper's latent size (the authors' code defaults to 5)
DEFAULT_LATENT_DIM = 10
#: Recent transitions, and fresh latents per transition, on which the routing statistics are measured
ROUTING_TRANSITIONS = 256
ROUTING_LATENT_DRAWS = 8


class IET(MASAC):
    """
    IET on a CTDE task (our cooperative adaptation, see the module's docstring): MASAC with per-agent soft-modular
    actors (:class:`~sb3_sera.iet.policies.IETPolicy`) conditioned on per-agent latents ``z ~ N(0, I)`` drawn at
    every episode start; the twin centralized critics read the state, every latent and the joint action.

    Takes MASAC's arguments (``IET("CTDEPolicy", env, learning_rate=..., compile_update=True, ...)``) and

    :param latent_dim: size of each agent's latent (the paper's 10), keyword only

    The model's env is the given CTDE env wrapped in :class:`.LatentVecEnv`, which adds the
    latents to the observations (``"latent"``, shape ``(n_agents, latent_dim)``) so that the replay buffer keeps
    them. ``predict`` also takes the CTDE env's own observations: it then draws the latents itself and returns them
    as the state to pass back, as ``evaluate_policy`` does. ``VecNormalize`` is not supported (its unnormalized
    observations, which the replay buffer stores, lack the latents). TensorBoard adds ``train/routing_entropy``
    (mean entropy of the actors' final routing weights on the last stored transitions: ``log(n_modules)`` when
    modules are mixed evenly), ``train/mixing_entropy`` (the same for the mixing between module layers) and
    ``train/routing_latent_std`` (standard deviation of the final routing weights over fresh latents for the same
    observations: how much the latent chooses among the modules).
    """

    single_agent: ClassVar[bool] = False
    acts_on_latents: ClassVar[bool] = True
    tunes_like: ClassVar[str | None] = None
    tuning: ClassVar[TuningSpace | None] = IET_TUNING

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"CTDEPolicy": IETPolicy}
    policy: IETPolicy

    @checks_keywords
    def __init__(
        self,
        policy: str | type[IETPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        compile_update: CompileMode = False,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        *,
        latent_dim: int = DEFAULT_LATENT_DIM,
    ):
        if isinstance(policy, str) and policy not in self.policy_aliases:
            raise ValueError(
                f"IET trains CTDE tasks with policy='CTDEPolicy' (per-agent soft-modular actors), got {policy!r}; "
                "on a single-agent task use SERASAC, SAC or SUNRISE"
            )
        self.latent_dim = check_int("latent_dim", latent_dim, 1)
        #: The latents' generator state when the model was saved (see :meth:`save` and :meth:`load`)
        self._latent_rng_state: dict[str, Any] | None = None
        arguments = constructor_arguments(locals())
        del arguments["latent_dim"]
        super().__init__(**arguments)

    def with_latents(self, env: VecEnv, seed: int | None = None) -> VecEnv:
        """
        ``env`` wrapped in :class:`.LatentVecEnv` (unless it already holds the latents), after checking it.

        :param env: a vectorized CTDE env with the model's agents
        :param seed: seed of the latents' generator
        """
        spaces = getattr(env.observation_space, "spaces", {})
        if LATENT_KEY in spaces:
            if spaces[LATENT_KEY].shape[-1] != self.latent_dim:
                raise ValueError(
                    f"This env already adds latents of size {spaces[LATENT_KEY].shape[-1]}, but latent_dim={self.latent_dim}"
                )
            return env
        if unwrap_vec_normalize(env) is not None:
            raise ValueError(
                "IET does not support VecNormalize: SB3 stores VecNormalize's unnormalized observations in the replay "
                "buffer, and those lack the latents IET adds outside the env; train without normalize"
            )
        return LatentVecEnv(env, len(agent_action_dims_of(env)), self.latent_dim, seed=seed)

    def _setup_model(self) -> None:
        if self.env is not None:
            self.env = self.with_latents(self.env)
            self.observation_space = self.env.observation_space
        super()._setup_model()

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """SB3's ``set_env``; the env (a CTDE env, or one already holding the latents) gets its latents."""
        super().set_env(self.with_latents(self._wrap_env(env, self.verbose)), force_reset)

    def latent_env(self) -> LatentVecEnv | None:
        """The :class:`.LatentVecEnv` that draws the latents of the model's env (None without an env)."""
        env = self.env
        while isinstance(env, VecEnvWrapper) and not isinstance(env, LatentVecEnv):
            env = env.venv
        return env if isinstance(env, LatentVecEnv) else None

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """SB3's ``save``, with the state of the latents' generator, which :meth:`load` restores."""
        latents = self.latent_env()
        self._latent_rng_state = None if latents is None else dict(latents.rng.bit_generator.state)
        super().save(path, exclude, include)

    @classmethod
    def load(
        cls: type[SelfIET],
        path: Any,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfIET:
        """
        SB3's ``load``; the saved model's spaces include the latents, so ``env`` gets them (:meth:`set_env`) first.
        Then ``env`` is seeded with the model's seed, as SB3's ``load`` seeds the env it is given, and its latents
        continue the generator of the saved model's (unless ``seed`` is given here: the latents then follow it), so
        that a loaded model continues the same way each time it is loaded.
        """
        model = super().load(
            path, None, device, custom_objects, print_system_info=print_system_info, force_reset=force_reset, **kwargs
        )
        if env is not None:
            vec_env = model._wrap_env(env, model.verbose)
            model.n_envs = vec_env.num_envs  # SB3's load takes the env's number of envs; set_env insists on the model's
            model.set_env(vec_env, force_reset=force_reset)
            assert model.env is not None
            if model.seed is not None:
                model.env.seed(model.seed)
            latents = model.latent_env()
            if latents is not None and model._latent_rng_state is not None and "seed" not in kwargs:
                latents.rng.bit_generator.state = model._latent_rng_state
        return model

    def dump_logs(self) -> None:
        if self.replay_buffer is not None and self.replay_buffer.size() > 0:
            self._record_routing()
        super().dump_logs()

    def _record_routing(self) -> None:
        """The routing statistics on the last stored transitions, with a generator of their own (training's untouched)."""
        assert self.replay_buffer is not None
        buffer = self.replay_buffer
        assert isinstance(buffer.observations, dict)  # a DictReplayBuffer: CTDE observations
        count = min(buffer.size(), max(1, ROUTING_TRANSITIONS // buffer.n_envs))
        indices = (np.arange(-count, 0) + buffer.pos) % buffer.buffer_size
        observations = {
            key: buffer.to_torch(values[indices].reshape(-1, *values.shape[2:])) for key, values in buffer.observations.items()
        }
        rng = np.random.default_rng(0)
        n_samples, n_agents, latent_dim = observations[LATENT_KEY].shape
        with th.no_grad():
            matrices, finals = self.policy.routing(observations)
            fresh = [
                self.policy.routing(
                    {**observations, LATENT_KEY: buffer.to_torch(draw_latents(rng, n_samples, n_agents, latent_dim))}
                )[1]
                for _ in range(ROUTING_LATENT_DRAWS)
            ]
        self.logger.record("train/routing_entropy", float(routing_entropy(finals)))
        self.logger.record("train/mixing_entropy", float(routing_entropy(matrices)))
        self.logger.record("train/routing_latent_std", float(th.stack(fresh).std(dim=0).mean()))
