"""TD3's (and DDPG's) updates inside a compiled gradient step, masked by whether every value before them was finite."""

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch as th
from stable_baselines3.common.policies import BaseModel
from torch import nn

from sb3_sera.common.compiled.adam import AdamPlan, AdamState, all_finite, masked_adam, masked_polyak

#: What a compiled TD3 gradient step checks (:func:`masked_td3_update`), a cause before its consequences
TD3_QUANTITIES = ("TD target", "critic loss", "critic gradients", "actor loss", "actor gradients")


class TD3Update(NamedTuple):
    """What :func:`masked_td3_update` gives back (tensors of the graph)."""

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (the actor's included)
    applied: th.Tensor
    #: One flag per quantity of ``TD3_QUANTITIES``
    finite: th.Tensor
    #: The actor's loss against the updated critics (computed at every step, applied where ``actor_update``)
    actor_loss: th.Tensor


def masked_td3_update(
    plans: Sequence[AdamPlan],
    states: Sequence[list[AdamState]],
    *,
    actor: nn.Module,
    actor_target: nn.Module,
    critic: nn.Module,
    critic_target: nn.Module,
    tau: float,
    target_q_values: th.Tensor,
    critic_loss: th.Tensor,
    actor_loss: Callable[[], th.Tensor],
    learning_rates: th.Tensor,
    actor_update: th.Tensor,
    healthy: th.Tensor,
) -> TD3Update:
    """
    The updates of a compiled TD3 gradient step, from its losses, in SB3's order: the critics, then, where
    ``actor_update`` (TD3's delayed policy update), the actor against the updated critics and the Polyak averages of
    the target critics and the target actor; each masked by ``healthy`` and by whether the values before it were
    finite. The actor's loss is computed at every step (a graph has no branch), its values checked only where it
    is applied. Inside a compiled graph.

    :param plans: the actor's and the critics' (:func:`td3_plans`)
    :param states: each plan's Adam state, in ``plans`` order
    :param actor_loss: computes the actor's loss, called after the critics' update
    :param learning_rates: each plan's rate, in ``plans`` order
    :param actor_update: whether the actor and the targets are updated after this step, a boolean scalar tensor
    :param healthy: whether every earlier step of the ``train()`` call had only finite values
    """
    actor_plan, critic_plan = plans
    critic_grads = th.autograd.grad(critic_loss, critic_plan.parameters())
    finite = [th.isfinite(target_q_values).all(), th.isfinite(critic_loss), all_finite(critic_grads)]
    apply = healthy & th.stack(finite).all()
    masked_adam(critic_plan, critic_grads, states[1], [learning_rates[1]] * len(critic_plan.settings), apply)
    loss = actor_loss()
    actor_grads = th.autograd.grad(loss, actor_plan.parameters())
    skipped = ~actor_update
    finite += [th.isfinite(loss) | skipped, all_finite(actor_grads) | skipped]
    applied = apply & finite[-2] & finite[-1]
    update = applied & actor_update
    masked_adam(actor_plan, actor_grads, states[0], [learning_rates[0]] * len(actor_plan.settings), update)
    masked_polyak(list(critic_target.parameters()), list(critic.parameters()), tau, update)
    masked_polyak(list(actor_target.parameters()), list(actor.parameters()), tau, update)
    return TD3Update(applied=applied, finite=th.stack(finite), actor_loss=loss)


def td3_plans(actor: BaseModel, critic: BaseModel) -> list[AdamPlan]:
    """The Adam plans of a TD3's optimizers, the actor's and the critics', in :func:`masked_td3_update`'s order."""
    return [
        AdamPlan(actor.optimizer, "actor", lambda: list(actor.parameters())),
        AdamPlan(critic.optimizer, "critic", lambda: list(critic.parameters())),
    ]
