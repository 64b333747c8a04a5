"""SAC's updates inside a compiled gradient step, masked by whether every value before them was finite."""

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch as th
from stable_baselines3.common.policies import BaseModel
from torch import nn

from sb3_sera.common.compiled.adam import AdamPlan, AdamState, all_finite, masked_adam, masked_polyak

#: What a compiled SAC gradient step checks (:func:`masked_sac_update`), in the order in which a cause precedes its
#: consequences; ``checked`` quantities of an algorithm's own come after the losses (:func:`sac_quantities`)
SAC_LOSSES = ("entropy coefficient", "TD target", "critic loss", "entropy coefficient loss")
SAC_GRADIENTS = ("critic gradients", "entropy coefficient gradient", "actor loss", "actor gradients")
#: SAC's logged values, in the order :func:`masked_sac_update`'s callers stack them (the last one where it is learned)
SAC_LOGGED = ("ent_coef", "critic_loss", "actor_loss", "ent_coef_loss")


def sac_quantities(checked: Sequence[str] = ()) -> tuple[str, ...]:
    """The quantities :func:`masked_sac_update` checks, with ``checked`` (an algorithm's own) after the losses."""
    return (*SAC_LOSSES, *checked, *SAC_GRADIENTS)


class SACUpdate(NamedTuple):
    """What :func:`masked_sac_update` gives back (tensors of the graph)."""

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (the actor's included)
    applied: th.Tensor
    #: One flag per quantity checked, in the order of :func:`sac_quantities`
    finite: th.Tensor
    #: The actor's loss against the updated critics
    actor_loss: th.Tensor


def masked_sac_update(
    plans: Sequence[AdamPlan],
    states: Sequence[list[AdamState]],
    *,
    critic: nn.Module,
    critic_target: nn.Module | None,
    tau: float,
    ent_coef: th.Tensor,
    ent_coef_loss: th.Tensor | None,
    target_q_values: th.Tensor,
    critic_loss: th.Tensor,
    actor_loss: Callable[[], th.Tensor],
    learning_rates: th.Tensor,
    target_update: th.Tensor,
    healthy: th.Tensor,
    checked: Sequence[th.Tensor] = (),
    critic_rates: Callable[[th.Tensor], Sequence[th.Tensor]] | None = None,
) -> SACUpdate:
    """
    The updates of a compiled SAC gradient step, from its losses, in SB3's order: the entropy coefficient, the
    critics, then the actor against the updated critics, and the target critics' Polyak average; each masked by
    ``healthy`` and by whether the values before it were finite. Inside a compiled graph.

    :param plans: the actor's, the critics' and, where the coefficient is learned, the entropy coefficient's
    :param states: each plan's Adam state (:meth:`.AdamPlan.state`), in ``plans`` order
    :param critic: the online critics, whose parameters the target critics (``critic_target``) follow at rate ``tau``
        (None: critics without targets)
    :param ent_coef_loss: None where the entropy coefficient is fixed
    :param actor_loss: computes the actor's loss, called after the critics' update
    :param learning_rates: each plan's rate, in ``plans`` order
    :param target_update: whether the target critics are updated after this step, a boolean scalar tensor
    :param healthy: whether every earlier step of the ``train()`` call had only finite values
    :param checked: flags of an algorithm's own quantities (each a boolean scalar tensor), checked after the losses
    :param critic_rates: called with the step's ``apply`` flag before the critics' step, gives each of the critic
        optimizer's groups its rate (an algorithm's own step sizes); by default every group's is the critic plan's
    """
    actor_plan, critic_plan = plans[:2]
    critic_grads = th.autograd.grad(critic_loss, critic_plan.parameters())
    entropy_grads: tuple[th.Tensor, ...] = ()
    if ent_coef_loss is not None:
        entropy_grads = th.autograd.grad(ent_coef_loss, plans[2].parameters())
    finite = [
        th.isfinite(ent_coef).all(),
        th.isfinite(target_q_values).all(),
        th.isfinite(critic_loss),
        th.isfinite(ent_coef_loss) if ent_coef_loss is not None else healthy,
        *checked,
        all_finite(critic_grads),
        all_finite(entropy_grads) if entropy_grads else healthy,
    ]
    apply = healthy & th.stack(finite).all()
    group_rates = critic_rates(apply) if critic_rates is not None else [learning_rates[1]] * len(critic_plan.settings)
    if ent_coef_loss is not None:
        masked_adam(plans[2], entropy_grads, states[2], [learning_rates[2]], apply)
    masked_adam(critic_plan, critic_grads, states[1], group_rates, apply)
    loss = actor_loss()
    actor_grads = th.autograd.grad(loss, actor_plan.parameters())
    finite += [th.isfinite(loss), all_finite(actor_grads)]
    applied = apply & finite[-2] & finite[-1]
    masked_adam(actor_plan, actor_grads, states[0], [learning_rates[0]] * len(actor_plan.settings), applied)
    if critic_target is not None:
        masked_polyak(list(critic_target.parameters()), list(critic.parameters()), tau, applied & target_update)
    return SACUpdate(applied=applied, finite=th.stack(finite), actor_loss=loss)


def sac_logged(
    ent_coef: th.Tensor, critic_loss: th.Tensor, actor_loss: th.Tensor, ent_coef_loss: th.Tensor | None
) -> th.Tensor:
    """A SAC step's values of ``SAC_LOGGED`` as one tensor (the entropy coefficient's loss where it is learned)."""
    logged = [ent_coef.reshape(()), critic_loss.detach(), actor_loss.detach()]
    return th.stack(logged if ent_coef_loss is None else [*logged, ent_coef_loss.detach()])


def sac_plans(
    actor: BaseModel,
    critic: BaseModel,
    ent_coef_optimizer: th.optim.Optimizer | None,
    log_ent_coef: th.Tensor | None,
    critic_parameters: Callable[[], list[th.Tensor]] | None = None,
) -> list[AdamPlan]:
    """
    The Adam plans of a SAC's optimizers: the actor's, the critics' and, when the entropy coefficient is learned
    (``ent_coef_optimizer`` and ``log_ent_coef``), its own, in :func:`masked_sac_update`'s order.

    :param critic_parameters: the critic optimizer's parameters in its order, through ``critic``'s modules (default:
        ``critic.parameters()``)
    """
    plans = [
        AdamPlan(actor.optimizer, "actor", lambda: list(actor.parameters())),
        AdamPlan(critic.optimizer, "critic", critic_parameters or (lambda: list(critic.parameters()))),
    ]
    if ent_coef_optimizer is not None and log_ent_coef is not None:
        plans.append(AdamPlan(ent_coef_optimizer, "entropy coefficient", lambda: [log_ent_coef]))
    return plans
