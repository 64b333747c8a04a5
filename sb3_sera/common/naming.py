"""What every algorithm of the package shares with SB3's own: its TensorBoard runs are named after it."""

from typing import TypeVar

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback

SelfNamedRuns = TypeVar("SelfNamedRuns", bound="NamedRuns")


class NamedRuns(BaseAlgorithm):
    """
    First in an algorithm's bases: ``learn``'s TensorBoard run is named after the algorithm's class (``SERASAC_1``,
    ``IET_1``, ...), as each SB3 algorithm writes out its own name as ``tb_log_name``'s default.
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
        """SB3's ``learn``; ``tb_log_name`` defaults to the algorithm's class name."""
        return super().learn(  # type: ignore[safe-super]  # the SB3 algorithm after this class in the bases
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=type(self).__name__ if tb_log_name is None else tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
