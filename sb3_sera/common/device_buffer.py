"""
Replay buffers on the model's device: SB3's ``ReplayBuffer`` and ``DictReplayBuffer`` with their transitions kept in
torch tensors on the buffer's device and their batches drawn there, so that no batch crosses from the host.

Each is an SB3 buffer (same constructor, ``add``, ``sample``, ``size``, ``n_envs``, ``handle_timeout_termination``) and
goes wherever SB3 takes ``replay_buffer_class``. A batch is drawn with torch's generator on the buffer's device (SB3's
buffers draw with NumPy's), so ``set_random_seed`` makes it repeatable. ``sample_batches`` draws a ``train()`` call's
batches at once, as SBX does. ``save_replay_buffer`` writes the transitions as NumPy arrays, so a buffer saved on a GPU
loads on a machine without one; ``load_replay_buffer`` of an algorithm that compiles its update puts it on the model's
device.

Not supported, each refused with a ``ValueError`` naming it: ``optimize_memory_usage`` (the next observations are
stored), and ``VecNormalize`` (SB3 normalizes a sampled batch with the env's NumPy statistics, on the host).
"""

from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

#: The fields a device buffer stores, in SB3's order (``timeouts`` only where timeouts are handled)
FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def _torch_dtype(dtype: Any) -> th.dtype:
    return th.from_numpy(np.zeros(0, dtype=dtype)).dtype


def _map(function: Any, value: Any) -> Any:
    """``function`` of a tensor or array, or of each entry of a dict of them."""
    if isinstance(value, dict):
        return {key: function(entry) for key, entry in value.items()}
    return function(value)


def _copy_into(target: th.Tensor, value: Any) -> None:
    target.copy_(th.as_tensor(np.asarray(value)).reshape(target.shape))


class DeviceReplayBuffer(ReplayBuffer):
    """
    SB3's ``ReplayBuffer`` with its transitions in tensors on ``device`` and its batches drawn there (see the module's
    docstring).

    :param buffer_size: Max number of element in the buffer
    :param observation_space: Observation space
    :param action_space: Action space
    :param device: PyTorch device of the stored transitions and of the batches
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: must be False (refused: the next observations are stored)
    :param handle_timeout_termination: Handle timeout termination (due to timelimit) separately and treat the task
        as infinite horizon task.
    """

    #: The tensors that hold the transitions (moved, saved and loaded together); a subclass adds its own
    stored_fields: ClassVar[tuple[str, ...]] = FIELDS
    # SB3's buffers declare NumPy arrays; these hold tensors on the buffer's device
    observations: Any
    next_observations: Any
    actions: Any
    rewards: Any
    dones: Any
    timeouts: Any

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
    ):
        if optimize_memory_usage:
            raise ValueError(
                f"{type(self).__name__} does not support optimize_memory_usage=True (it stores the next observations); "
                "use optimize_memory_usage=False, or SB3's ReplayBuffer"
            )
        BaseBuffer.__init__(self, buffer_size, observation_space, action_space, device, n_envs=n_envs)
        self.buffer_size = max(buffer_size // n_envs, 1)
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        observation_dtypes = _map(_torch_dtype, self._observation_dtypes())
        self.observations = self._zeros(self.obs_shape, observation_dtypes)
        self.next_observations = self._zeros(self.obs_shape, observation_dtypes)
        action_dtype = _torch_dtype(self._maybe_cast_dtype(action_space.dtype))
        self.actions = self._zeros((self.action_dim,), action_dtype)
        self.rewards = self._zeros((), th.float32)
        self.dones = self._zeros((), th.float32)
        self.timeouts = self._zeros((), th.float32)

    def _observation_dtypes(self) -> Any:
        return self.observation_space.dtype

    def _zeros(self, shape: Any, dtype: Any) -> Any:
        """Zeros of ``(buffer_size, n_envs, *shape)`` on the device; a dict of them for a dict of shapes."""
        if isinstance(shape, dict):
            return {key: self._zeros(shape[key], dtype[key]) for key in shape}
        return th.zeros((self.buffer_size, self.n_envs, *shape), dtype=dtype, device=self.device)

    def add(
        self,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        for target, value in ((self.observations, obs), (self.next_observations, next_obs)):
            if isinstance(target, dict):
                for key, entry in target.items():
                    _copy_into(entry[self.pos], value[key])
            else:
                _copy_into(target[self.pos], value)
        _copy_into(self.actions[self.pos], action)
        _copy_into(self.rewards[self.pos], reward)
        _copy_into(self.dones[self.pos], done)
        if self.handle_timeout_termination:
            _copy_into(self.timeouts[self.pos], [info.get("TimeLimit.truncated", False) for info in infos])
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True
            self.pos = 0

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> Any:
        """A batch of ``batch_size`` transitions drawn uniformly on the device (with replacement, as SB3's)."""
        return self.sample_batches(1, batch_size, env)[0]

    def sample_batches(self, n_batches: int, batch_size: int, env: VecNormalize | None = None) -> list[Any]:
        """
        ``n_batches`` batches of ``batch_size`` transitions drawn at once (one draw and one gather for all of them):
        a ``train()`` call's batches.
        """
        if env is not None:
            raise ValueError(
                f"{type(self).__name__} does not support VecNormalize: SB3 normalizes a sampled batch with the env's "
                "NumPy statistics on the host; train without VecNormalize, or with SB3's ReplayBuffer"
            )
        filled = self.buffer_size if self.full else self.pos
        if filled == 0:
            raise ValueError(f"{type(self).__name__} is empty: add transitions before sampling")
        total = n_batches * batch_size
        indices = th.randint(filled, (total,), device=self.device)
        samples = self._get_samples(indices)
        parts = {
            name: _map(lambda tensor: tensor.split(batch_size), field)
            for name, field in samples._asdict().items()
            if field is not None
        }
        return [
            type(samples)(**{name: _map(lambda split, i=index: split[i], part) for name, part in parts.items()})
            for index in range(n_batches)
        ]

    def _get_samples(self, batch_inds: Any, env: VecNormalize | None = None) -> Any:
        """The transitions at ``batch_inds``, each from an env drawn uniformly (as SB3's)."""
        batch_inds = th.as_tensor(batch_inds, device=self.device)
        return self._samples_at(batch_inds, th.randint(self.n_envs, batch_inds.shape, device=self.device))

    def _samples_at(self, batch_inds: th.Tensor, env_inds: th.Tensor) -> Any:
        """The transitions at ``batch_inds`` of the envs ``env_inds``, as SB3's samples."""

        def gather(field: th.Tensor) -> th.Tensor:
            return field[batch_inds, env_inds]

        # Only the dones that are not due to timeouts
        dones = self.dones[batch_inds, env_inds] * (1 - self.timeouts[batch_inds, env_inds])
        return self._samples_class()(
            observations=_map(gather, self.observations),
            actions=gather(self.actions),
            next_observations=_map(gather, self.next_observations),
            dones=dones.reshape(-1, 1),
            rewards=gather(self.rewards).reshape(-1, 1),
        )

    def _samples_class(self) -> type[ReplayBufferSamples] | type[DictReplayBufferSamples]:
        return ReplayBufferSamples

    def to(self, device: th.device | str) -> None:
        """Move the stored transitions to ``device`` (and draw batches there)."""
        self.device = th.device(device)
        for name in self.stored_fields:
            setattr(self, name, _map(lambda tensor: tensor.to(self.device), getattr(self, name)))

    def __getstate__(self) -> dict[str, Any]:
        # NumPy arrays: a buffer saved on a GPU loads on a machine without one
        state = self.__dict__.copy()
        for name in self.stored_fields:
            state[name] = _map(lambda tensor: tensor.cpu().numpy(), state[name])
        state["device"] = str(self.device)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        device = th.device(state["device"])
        if device.type == "cuda" and not th.cuda.is_available():
            device = th.device("cpu")
        self.__dict__.update(state, device=device)
        for name in self.stored_fields:
            setattr(self, name, _map(lambda array: th.from_numpy(array).to(device), state[name]))


class DeviceDictReplayBuffer(DeviceReplayBuffer, DictReplayBuffer):
    """
    SB3's ``DictReplayBuffer`` (Dict observations, the multi-agent tasks') on the device: :class:`DeviceReplayBuffer`
    with a tensor per observation key.

    :param buffer_size: Max number of element in the buffer
    :param observation_space: Observation space (a ``Dict``)
    :param action_space: Action space
    :param device: PyTorch device of the stored transitions and of the batches
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: must be False (refused, as SB3's ``DictReplayBuffer`` refuses it)
    :param handle_timeout_termination: Handle timeout termination (due to timelimit) separately and treat the task
        as infinite horizon task.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
    ):
        if not isinstance(observation_space, spaces.Dict):
            raise TypeError(f"DeviceDictReplayBuffer needs a Dict observation space, got {observation_space}")
        super().__init__(
            buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage, handle_timeout_termination
        )

    def _observation_dtypes(self) -> Any:
        assert isinstance(self.observation_space, spaces.Dict)
        return {key: space.dtype for key, space in self.observation_space.spaces.items()}

    def _samples_class(self) -> type[ReplayBufferSamples] | type[DictReplayBufferSamples]:
        return DictReplayBufferSamples


def device_buffer_class(observation_space: spaces.Space) -> type[DeviceReplayBuffer]:
    """The device buffer for ``observation_space``: :class:`DeviceDictReplayBuffer` for a ``Dict``, else the plain one."""
    return DeviceDictReplayBuffer if isinstance(observation_space, spaces.Dict) else DeviceReplayBuffer
