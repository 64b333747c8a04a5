"""
Variance-adaptive critic step size of SERA (paper section 4.2, appendix B.1.4, docs/SPEC.md section 1 step 6).

Each critic ``i`` gets the Kalman-like gain ``kappa_i = P_i / (P_i + R_i + eta)`` from two batch variances,
and its learning rate ``lr_i = lr_max * (kappa_min + (1 - kappa_min) * kappa_i)``. The rate is applied as the
optimizer's step size for that critic: Adam is invariant to the scale of the loss, so scaling the loss or
the gradient by ``kappa`` would change nothing.
"""

from typing import NamedTuple

import torch as th
from torch import nn


def batch_variance(values: th.Tensor) -> th.Tensor:
    """
    Variance over the batch (first) dimension, without Bessel's correction.

    :param values: shape ``(batch_size, ...)``
    :return: shape ``values.shape[1:]``
    """
    return values.var(dim=0, correction=0)


def ema(previous: th.Tensor, value: th.Tensor, decay: float, initialized: th.Tensor) -> th.Tensor:
    """
    Exponential moving average ``decay * previous + (1 - decay) * value`` that starts from the first value.

    :param previous: the running average
    :param value: the new observation
    :param decay: the weight of the past, in ``[0, 1)``
    :param initialized: boolean scalar tensor; when false the average starts at ``value`` (no zero bias)
    :return: the new running average (a new tensor)
    """
    return th.where(initialized, decay * previous + (1.0 - decay) * value, value)


def kalman_gain(estimation_var: th.Tensor, measurement_var: th.Tensor, eps: float = 1e-8) -> th.Tensor:
    """
    ``kappa = P / (P + R + eta)`` (paper eq. 12), in ``[0, 1)`` for non-negative variances.

    :param estimation_var: estimation variance ``P``
    :param measurement_var: measurement variance ``R``
    :param eps: ``eta > 0``, for numerical stability
    """
    return estimation_var / (estimation_var + measurement_var + eps)


#: Critic learning rate at full gain ``kappa = 1``: SERASAC's default, chosen by measurement (the paper's is 5e-4,
#: appendix B.1.4; :data:`~sb3_sera.sera.sera.PAPER_RATES`)
DEFAULT_CRITIC_LR_MAX = 1e-3


def critic_learning_rates(
    kappa: th.Tensor, lr_max: float | th.Tensor = DEFAULT_CRITIC_LR_MAX, kappa_min: float = 0.2
) -> th.Tensor:
    """
    Map gains to learning rates ``lr_max * (kappa_min + (1 - kappa_min) * kappa)`` (paper eq. 16).

    With the defaults, rates lie in ``[2e-4, 1e-3]``.

    :param kappa: gains in ``[0, 1]``
    :param lr_max: the learning rate at ``kappa = 1`` (a float or a scalar tensor)
    :param kappa_min: the floor of the rescaled gain, in ``[0, 1]``
    """
    return lr_max * (kappa_min + (1.0 - kappa_min) * kappa)


class StepSizeUpdate(NamedTuple):
    """One step of :class:`VarianceAdaptiveStepSize`, computed but not yet committed."""

    #: TD-residual variance EMA ``v`` (eq. 10), shape ``(n_critics,)``
    td_error_var: th.Tensor
    #: Estimation variance EMA ``P`` (eq. 11), shape ``(n_critics,)``
    estimation_var: th.Tensor
    #: Measurement variance ``R`` of this batch (eq. 9), shape ``(n_critics,)``
    measurement_var: th.Tensor
    #: Gains ``kappa`` (eq. 12), shape ``(n_critics,)``
    kappa: th.Tensor
    #: Learning rates (eq. 16), shape ``(n_critics,)``
    learning_rates: th.Tensor


class VarianceAdaptiveStepSize(nn.Module):
    """
    Running state of the variance-adaptive step size, one entry per critic.

    The state lives in buffers, so it is saved and loaded with the model and training continues from it.
    :meth:`compute` is side-effect free; :meth:`commit` stores its result (after the caller checked it is finite).
    ``lr_max`` is a buffer too, not saved: the algorithm sets it from its schedule (:meth:`set_lr_max`), and a
    compiled update reads the new value without recompiling.

    :param n_critics: number of critics
    :param td_variance_ema: ``b_v``, weight of the past in the TD-residual variance EMA, in ``[0, 1)``
    :param estimation_variance_ema: ``b_P``, weight of the past in the estimation variance EMA, in ``[0, 1)``
    :param kappa_eps: ``eta > 0`` in the gain
    :param lr_max: critic learning rate at ``kappa = 1``
    :param kappa_min: floor of the rescaled gain, in ``[0, 1]``
    """

    td_error_var: th.Tensor
    estimation_var: th.Tensor
    initialized: th.Tensor
    lr_max: th.Tensor

    def __init__(
        self,
        n_critics: int,
        td_variance_ema: float = 0.9,
        estimation_variance_ema: float = 0.9,
        kappa_eps: float = 1e-8,
        lr_max: float = DEFAULT_CRITIC_LR_MAX,
        kappa_min: float = 0.2,
    ):
        super().__init__()
        self.td_variance_ema = td_variance_ema
        self.estimation_variance_ema = estimation_variance_ema
        self.kappa_eps = kappa_eps
        self.kappa_min = kappa_min
        self.register_buffer("td_error_var", th.zeros(n_critics))
        self.register_buffer("estimation_var", th.zeros(n_critics))
        self.register_buffer("initialized", th.tensor(False))
        self.register_buffer("lr_max", th.tensor(float(lr_max)), persistent=False)

    def set_lr_max(self, lr_max: float) -> None:
        """Set the critic learning rate at full gain (the value of the algorithm's schedule)."""
        self.lr_max.fill_(lr_max)

    def compute(self, td_errors: th.Tensor, target_deviations: th.Tensor) -> StepSizeUpdate:
        """
        Compute the next state and the learning rates from one batch.

        :param td_errors: ``delta_i = y - Q_i(s, a)``, shape ``(batch_size, n_critics)``, detached
        :param target_deviations: ``q_i - Q_SERA`` of the target critics at ``(s', a')``,
            shape ``(batch_size, n_critics)``, detached
        """
        td_error_var = ema(self.td_error_var, batch_variance(td_errors), self.td_variance_ema, self.initialized)
        estimation_var = ema(self.estimation_var, td_error_var, self.estimation_variance_ema, self.initialized)
        measurement_var = batch_variance(target_deviations)
        kappa = kalman_gain(estimation_var, measurement_var, self.kappa_eps)
        learning_rates = critic_learning_rates(kappa, self.lr_max, self.kappa_min)
        return StepSizeUpdate(td_error_var, estimation_var, measurement_var, kappa, learning_rates)

    def commit(self, update: StepSizeUpdate, apply: th.Tensor | None = None) -> None:
        """
        Store the running averages of ``update`` as the new state; with ``apply``, a boolean scalar tensor, only
        where it is true (a compiled step decides on the device whether its values were finite).
        """
        if apply is None:
            self.td_error_var.copy_(update.td_error_var)
            self.estimation_var.copy_(update.estimation_var)
            self.initialized.fill_(True)
            return
        self.td_error_var.copy_(th.where(apply, update.td_error_var, self.td_error_var))
        self.estimation_var.copy_(th.where(apply, update.estimation_var, self.estimation_var))
        self.initialized.copy_(self.initialized | apply)
