"""
What every algorithm of the package shares with SB3's own: its TensorBoard runs are named after it; and what it adds:
a warning when ``learn`` would end before the first gradient step, an error for a negative budget, and a warning
(once a process) when torch's threads outnumber the cores the process may run on.
"""

import os
import warnings
from typing import TypeVar

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback

SelfNamedRuns = TypeVar("SelfNamedRuns", bound="NamedRuns")

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
    trains nothing (``sb3-sera train -n 600`` with a MuJoCo entry's ``learning_starts: 10000``).
    """

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
