"""The parts of an off-policy ``train()`` that SERASAC and SUNRISE share with SB3's SAC, written once."""

import torch as th
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm


def start_train(model: OffPolicyAlgorithm, optimizers: list[th.optim.Optimizer]) -> None:
    """What SB3's SAC does before its gradient steps: training mode on, the learning-rate schedules applied."""
    model.policy.set_training_mode(True)
    model._update_learning_rate(optimizers)


def target_update_due(n_updates: int, gradient_step: int, interval: int) -> bool:
    """
    Whether the target networks are updated after ``gradient_step`` of this ``train()`` call: every ``interval``
    gradient steps counted across calls (SB3's SAC restarts its count at each call, so with ``gradient_steps=1``
    it updates at every step whatever the interval).
    """
    return (n_updates + gradient_step) % interval == 0


def record_means(logger: Logger, logged: dict[str, list[th.Tensor]], prefix: str = "train/") -> None:
    """Record the mean of each list of per-step scalars, read back from the device in one transfer."""
    if not logged:
        return
    means = th.stack([th.stack(values).mean() for values in logged.values()]).tolist()
    for key, value in zip(logged, means, strict=True):
        logger.record(f"{prefix}{key}", value)
