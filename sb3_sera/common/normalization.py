"""
Normalized critics, as SB3 users know them from SBX and sb3-contrib: LayerNorm and dropout after each hidden layer
(DroQ's critics, SBX's ``layer_norm`` and ``dropout_rate``), or batch renormalization before each linear layer
(CrossQ's critics, sb3-contrib's ``batch_norm`` and its ``BatchRenorm1d``), built with SB3's ``create_mlp``.
"""

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch as th
from sb3_contrib.common.torch_layers import BatchRenorm1d
from torch import nn

from sb3_sera.common.hyperparameters import check_choice, check_int, check_range


class BatchRenorm(BatchRenorm1d):
    """
    sb3-contrib's ``BatchRenorm1d`` (same parameters, buffers, defaults and numbers) whose forward pass has no branch
    on a tensor's value, so that a gradient step holding it compiles into one graph: after the warm-up the
    renormalization's ``r`` and ``d`` are used, during it ``r = 1`` and ``d = 0`` (batch normalization), chosen with
    ``torch.where`` rather than ``if self.steps > self.warmup_steps``.
    """

    ra_mean: th.Tensor
    ra_var: th.Tensor
    steps: th.Tensor

    def forward(self, x: th.Tensor) -> th.Tensor:
        """
        Normalize ``x`` by its batch statistics, renormalized toward the running ones after the warm-up, and update
        the running statistics (in training mode); by the running statistics alone in evaluation mode.

        :param x: shape ``(batch_size, num_features)``
        """
        if self.training:
            batch_mean = x.mean(dim=0)
            batch_var = x.var(dim=0)
            running_std = (self.ra_var + self.eps).sqrt()
            renorm = self.steps > self.warmup_steps
            r = ((batch_var + self.eps).sqrt() / running_std).detach().clamp(1 / self.rmax, self.rmax)
            d = ((batch_mean - self.ra_mean) / running_std).detach().clamp(-self.dmax, self.dmax)
            r = th.where(renorm, r, th.ones_like(r))
            d = th.where(renorm, d, th.zeros_like(d))
            mean = batch_mean - d * batch_var.sqrt() / r
            var = batch_var / r**2
            with th.no_grad():
                self.ra_mean += self.momentum * (batch_mean.detach() - self.ra_mean)
                self.ra_var += self.momentum * (batch_var.detach() - self.ra_var)
                self.steps += 1
        else:
            mean, var = self.ra_mean, self.ra_var
        x = (x - mean[None]) / (var[None] + self.eps).sqrt()
        return self.scale * x + self.bias if self.affine else x


def _dropout(rate: float, features: int) -> nn.Dropout:
    """``nn.Dropout(rate)``, built as SB3's ``create_mlp`` builds a post-linear module (from the features' number)."""
    return nn.Dropout(rate)


@dataclass(frozen=True)
class CriticNorm:
    """
    How each critic's hidden layers are normalized: the policy keyword arguments ``layer_norm``, ``dropout_rate``
    (DroQ: ``True, 0.01``), ``batch_norm`` (CrossQ), ``batch_norm_momentum``, ``batch_norm_eps`` and
    ``renorm_warmup_steps``, checked (:meth:`checked`).
    """

    #: LayerNorm after each hidden linear layer (after its dropout), before the activation
    layer_norm: bool = False
    #: Dropout rate after each hidden linear layer, in [0, 1); 0: none
    dropout_rate: float = 0.0
    #: Batch renormalization before each linear layer; the critics then train without target networks
    batch_norm: bool = False
    #: Rate at which the running statistics follow the batches', in (0, 1]
    batch_norm_momentum: float = 0.01
    #: Added to the variances, > 0
    batch_norm_eps: float = 0.001
    #: Forward passes in training mode before the running statistics renormalize the batches' (batch normalization
    #: until then), >= 0
    renorm_warmup_steps: int = 100_000

    def checked(self) -> "CriticNorm":
        """
        These settings with numbers as Python types; ``ValueError`` naming the setting and what is allowed for a value
        out of range, or for batch renormalization together with LayerNorm or dropout.
        """
        for name in ("layer_norm", "batch_norm"):
            check_choice(name, getattr(self, name), (True, False))
        dropout_rate = check_range("dropout_rate", self.dropout_rate, 0.0, 1.0, high_inclusive=False)
        momentum = check_range("batch_norm_momentum", self.batch_norm_momentum, 0.0, 1.0, low_inclusive=False)
        eps = check_range("batch_norm_eps", self.batch_norm_eps, 0.0, None, low_inclusive=False)
        warmup = check_int("renorm_warmup_steps", self.renorm_warmup_steps, 0)
        if self.batch_norm and (self.layer_norm or dropout_rate > 0):
            raise ValueError(
                f"batch_norm=True with layer_norm={self.layer_norm} and dropout_rate={dropout_rate}: choose one recipe, "
                "batch renormalization (CrossQ: batch_norm=True) or LayerNorm and dropout (DroQ: layer_norm=True, "
                "dropout_rate=0.01)"
            )
        return CriticNorm(self.layer_norm, dropout_rate, self.batch_norm, momentum, eps, warmup)

    @property
    def pre_linear_modules(self) -> list[Callable[[int], nn.Module]]:
        """SB3 ``create_mlp``'s ``pre_linear_modules``: batch renormalization, where asked for."""
        if not self.batch_norm:
            return []
        return [
            partial(
                BatchRenorm,
                momentum=self.batch_norm_momentum,
                eps=self.batch_norm_eps,
                warmup_steps=self.renorm_warmup_steps,
            )
        ]

    @property
    def post_linear_modules(self) -> list[Callable[[int], nn.Module]]:
        """SB3 ``create_mlp``'s ``post_linear_modules``: dropout, then LayerNorm (SBX's order), where asked for."""
        modules: list[Callable[[int], nn.Module]] = []
        if self.dropout_rate > 0:
            modules.append(partial(_dropout, self.dropout_rate))
        if self.layer_norm:
            modules.append(nn.LayerNorm)
        return modules

    def kwargs(self) -> dict[str, bool | float | int]:
        """The policy keyword arguments these settings come from (saved with the policy)."""
        return {
            "layer_norm": self.layer_norm,
            "dropout_rate": self.dropout_rate,
            "batch_norm": self.batch_norm,
            "batch_norm_momentum": self.batch_norm_momentum,
            "batch_norm_eps": self.batch_norm_eps,
            "renorm_warmup_steps": self.renorm_warmup_steps,
        }


def renorm_layers(module: nn.Module) -> list[BatchRenorm]:
    """The batch renormalization layers of ``module``, in module order."""
    return [layer for layer in module.modules() if isinstance(layer, BatchRenorm)]


def set_renorm_training(layers: list[BatchRenorm], mode: bool) -> None:
    """
    Put batch renormalization layers in training mode (batch statistics, running ones updated) or evaluation mode
    (running statistics), as sb3-contrib's ``set_bn_training_mode``; the flag is set directly (a compiled step traces it).
    """
    for layer in layers:
        layer.training = mode
