"""
What every algorithm of the package shares with SB3's own: its TensorBoard runs are named after it; and what it adds:
a warning when ``learn`` would end before the first gradient step, an error for a negative budget, a warning (once a
process) when torch's threads outnumber the cores the process may run on, and loads that say in one line why a file
does not fit (:mod:`sb3_sera.common.loading`).
"""

import io
import os
import pathlib
import warnings
from typing import Any, TypeVar

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback

from sb3_sera.common.loading import foreign_file_reason, other_networks_reason

SelfNamedRuns = TypeVar("SelfNamedRuns", bound="NamedRuns")
#: What SB3's ``load`` and ``set_parameters`` read a model from
LoadPath = str | pathlib.Path | io.BufferedIOBase

#: Whether this process was warned that torch's threads outnumber its cores
_warned_threads = False


def warn_if_threads_outnumber_cores() -> None:
    """
    Warn, once a process, where torch's threads outnumber the cores this process may run on (its CPU affinity, where
    the system tells it): small networks then train several times slower. Where the system does not tell, or the
    cores are busy with other processes, nothing can be told reliably and nothing is said.
    """
    global _warned_threads
    affinity = getattr(os, "sched_getaffinity", None)
    if _warned_threads or affinity is None:
        return
    cores, threads = len(affinity(0)), th.get_num_threads()
    if threads > cores:
        _warned_threads = True
        warnings.warn(
            f"torch runs {threads} threads but this process may use {cores} core(s): small networks then train several "
            f"times slower; call torch.set_num_threads({cores}) before training (one thread a process when several "
            "train at once)",
            stacklevel=3,
        )


class NamedRuns(BaseAlgorithm):
    """
    First in an algorithm's bases: ``learn``'s TensorBoard run is named after the algorithm's class (``SERASAC_1``,
    ``IET_1``, ...), as each SB3 algorithm writes out its own name as ``tb_log_name``'s default. An off-policy
    algorithm whose ``learning_starts`` lies at or beyond the end of the call warns, with the numbers: such a call
    trains nothing (``sb3-sera train -n 600`` with a MuJoCo entry's ``learning_starts: 10000``). ``load`` of another
    algorithm's file, and ``set_parameters`` of a file saved with other networks, raise ``ValueError`` saying so.
    """

    @classmethod
    def load(
        cls: type[SelfNamedRuns],
        path: LoadPath,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfNamedRuns:
        """
        SB3's ``load``.

        :raises ValueError: for a file of another algorithm (SB3's own error names an optimizer's key), naming its policy
        """
        try:
            return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        except (KeyError, RuntimeError) as error:
            reason = foreign_file_reason(cls, path)
            if reason is None:
                raise
            raise ValueError(reason) from error

    def set_parameters(
        self, load_path_or_dict: str | dict[str, th.Tensor], exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """
        SB3's ``set_parameters``.

        :raises ValueError: for a file whose networks differ from this model's (another ensemble size, other layers, or
            another algorithm), naming the ``policy_kwargs`` of both
        """
        try:
            super().set_parameters(load_path_or_dict, exact_match, device)
        except (KeyError, RuntimeError) as error:
            reason = None if isinstance(load_path_or_dict, dict) else other_networks_reason(self, load_path_or_dict)
            if reason is None:
                raise
            raise ValueError(reason) from error

    def learn(
        self: SelfNamedRuns,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfNamedRuns:
        """
        SB3's ``learn``; ``tb_log_name`` defaults to the algorithm's class name.

        :raises ValueError: for a negative ``total_timesteps`` (SB3 would return without a word)
        """
        if total_timesteps < 0:
            raise ValueError(
                f"{type(self).__name__}.learn: total_timesteps={total_timesteps} is negative: it is the number of "
                "environment steps to take, an integer >= 0"
            )
        warn_if_threads_outnumber_cores()
        learning_starts = getattr(self, "learning_starts", None)
        end = total_timesteps + (0 if reset_num_timesteps else self.num_timesteps)
        if learning_starts is not None and learning_starts >= end:
            warnings.warn(
                f"{type(self).__name__}.learn: learning_starts={learning_starts} is at or beyond the end of this call "
                f"({end} steps): it collects transitions but makes no gradient step, so the policy stays untrained; "
                "lower learning_starts or train for more steps",
                stacklevel=2,
            )
        return super().learn(  # type: ignore[safe-super]  # the SB3 algorithm after this class in the bases
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=type(self).__name__ if tb_log_name is None else tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
