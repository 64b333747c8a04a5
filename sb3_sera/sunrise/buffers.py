"""
SUNRISE's replay buffers: SB3's, or the device one (:class:`~sb3_sera.common.device_buffer.DeviceReplayBuffer`), plus
each transition's bootstrap masks, drawn once when it is stored.
"""

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sera.common.device_buffer import FIELDS, DeviceReplayBuffer
from sb3_sera.common.hyperparameters import check_int, check_range


class SUNRISEReplayBufferSamples(NamedTuple):
    """SB3's ``ReplayBufferSamples`` with the bootstrap masks of the sampled transitions."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    #: Which members train on each transition, shape ``(batch_size, n_members)``, 0 or 1
    masks: th.Tensor
    #: Always None (no n-step returns), for code written against SB3's samples
    discounts: th.Tensor | None = None


def bootstrap_masks(n_transitions: int, n_members: int, bootstrap_prob: float) -> np.ndarray:
    """
    Bernoulli(``bootstrap_prob``) masks, one per transition and member; a transition that no member drew goes to
    one member chosen uniformly (the authors' rule: every transition trains at least one member).

    :param n_transitions: number of transitions
    :param n_members: ensemble size
    :param bootstrap_prob: probability that a member trains on a transition
    :return: shape ``(n_transitions, n_members)``, float32 zeros and ones
    """
    masks = (np.random.random((n_transitions, n_members)) < bootstrap_prob).astype(np.float32)
    empty = np.flatnonzero(masks.sum(axis=1) == 0)
    masks[empty, np.random.randint(n_members, size=len(empty))] = 1.0
    return masks


def mask_settings(n_members: int, bootstrap_prob: float) -> tuple[int, float]:
    """
    The masks' settings checked (``ValueError`` naming the one out of range): ``n_members`` an integer >= 1,
    ``bootstrap_prob`` in ``(0, 1]``.
    """
    return check_int("n_members", n_members, 1), check_range("bootstrap_prob", bootstrap_prob, 0.0, 1.0, low_inclusive=False)


class SUNRISEReplayBuffer(ReplayBuffer):
    """
    SB3's ``ReplayBuffer`` that also stores, for each transition, which of the ``n_members`` members train on it.

    The masks are drawn in ``add()`` and live in the buffer's arrays, so ``save_replay_buffer`` and
    ``load_replay_buffer`` keep them.

    :param buffer_size: Max number of element in the buffer
    :param observation_space: Observation space
    :param action_space: Action space
    :param device: PyTorch device
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param handle_timeout_termination: Handle timeout termination (due to timelimit) separately and treat the task
        as infinite horizon task.
    :param n_members: ensemble size ``N``
    :param bootstrap_prob: probability that a member trains on a transition, in ``(0, 1]`` (the authors' 0.5)
    """

    masks: np.ndarray

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_members: int = 5,
        bootstrap_prob: float = 0.5,
    ):
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=optimize_memory_usage,
            handle_timeout_termination=handle_timeout_termination,
        )
        self.n_members, self.bootstrap_prob = mask_settings(n_members, bootstrap_prob)
        self.masks = np.zeros((self.buffer_size, self.n_envs, self.n_members), dtype=np.float32)

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        self.masks[self.pos] = bootstrap_masks(self.n_envs, self.n_members, self.bootstrap_prob)
        super().add(obs, next_obs, action, reward, done, infos)

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> SUNRISEReplayBufferSamples:  # type: ignore[override]
        # SB3's ReplayBuffer._get_samples, which draws the env indices itself, plus the masks at the same indices
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        if self.optimize_memory_usage:
            next_obs = self.observations[(batch_inds + 1) % self.buffer_size, env_indices, :]
        else:
            next_obs = self.next_observations[batch_inds, env_indices, :]
        data = (
            self._normalize_obs(self.observations[batch_inds, env_indices, :], env),
            self.actions[batch_inds, env_indices, :],
            self._normalize_obs(next_obs, env),
            # Only use dones that are not due to timeouts
            (self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])).reshape(-1, 1),
            self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env),
            self.masks[batch_inds, env_indices, :],
        )
        return SUNRISEReplayBufferSamples(*tuple(map(self.to_torch, data)))


class SUNRISEDeviceReplayBuffer(DeviceReplayBuffer):
    """
    :class:`SUNRISEReplayBuffer` on the model's device: a
    :class:`~sb3_sera.common.device_buffer.DeviceReplayBuffer` that also stores each transition's bootstrap masks
    (drawn in ``add()`` as :class:`SUNRISEReplayBuffer` draws them) and returns them with the batch.

    :param buffer_size: Max number of element in the buffer
    :param observation_space: Observation space
    :param action_space: Action space
    :param device: PyTorch device of the stored transitions and of the batches
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: must be False (refused: the next observations are stored)
    :param handle_timeout_termination: Handle timeout termination (due to timelimit) separately and treat the task
        as infinite horizon task.
    :param n_members: ensemble size ``N``
    :param bootstrap_prob: probability that a member trains on a transition, in ``(0, 1]`` (the authors' 0.5)
    """

    stored_fields = (*FIELDS, "masks")

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_members: int = 5,
        bootstrap_prob: float = 0.5,
    ):
        super().__init__(
            buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage, handle_timeout_termination
        )
        self.n_members, self.bootstrap_prob = mask_settings(n_members, bootstrap_prob)
        self.masks = self._zeros((self.n_members,), th.float32)

    def add(
        self,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        masks = bootstrap_masks(self.n_envs, self.n_members, self.bootstrap_prob)
        self.masks[self.pos] = th.as_tensor(masks, device=self.device)
        super().add(obs, next_obs, action, reward, done, infos)

    def _samples_at(self, batch_inds: th.Tensor, env_inds: th.Tensor) -> SUNRISEReplayBufferSamples:
        samples = super()._samples_at(batch_inds, env_inds)
        return SUNRISEReplayBufferSamples(
            samples.observations,
            samples.actions,
            samples.next_observations,
            samples.dones,
            samples.rewards,
            masks=self.masks[batch_inds, env_inds],
        )
