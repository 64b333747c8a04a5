"""
SERASAC's ``compile_update``: its gradient step as one ``torch.compile`` graph. The step calls the functions of
:mod:`sb3_sera.sera.update` in the eager ``train()``'s order; it differs only in how updates are applied: gradients
from ``torch.autograd.grad``, Adam and the target update masked by whether every value so far was finite
(:func:`~sb3_sera.common.compiled.masked_adam`), and nothing read from the device until the ``train()`` call ends.
The actor's value is :func:`~sb3_sera.sera.update.actor_value_linearized` on a CPU (``train()``'s
:func:`~sb3_sera.sera.update.actor_value` without its second forward pass of the selected critic); on a GPU it is
:func:`~sb3_sera.sera.update.actor_value_gathered` (static shapes: no synchronisation, and CUDA graphs can replay the
step). The step reaches every parameter through the model's modules, never through an optimizer
(:class:`~sb3_sera.common.compiled.AdamPlan`).
"""

from functools import partial
from typing import Any, NamedTuple

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_sera.common.compiled import all_finite, masked_adam, masked_polyak, read_steps, run_steps
from sb3_sera.common.finite import gradient_step_context
from sb3_sera.sera.update import actor_value_gathered, actor_value_linearized, diagnostics

#: What a compiled gradient step checks, in the order in which a cause precedes its consequences
COMPILED_QUANTITIES = (
    "entropy coefficient",
    "TD target",
    "critic loss",
    "entropy coefficient loss",
    "critic step size",
    "critic gradients",
    "entropy coefficient gradient",
    "actor loss",
    "actor gradients",
)


class CompiledStepOutput(NamedTuple):
    """
    What one compiled gradient step gives back (:class:`~sb3_sera.common.compiled.StepOutput`): tensors only, nothing
    read from the device during the step.
    """

    #: Whether this step and every earlier one of the ``train()`` call had only finite values (their updates applied)
    healthy: th.Tensor
    #: One flag per quantity of :data:`COMPILED_QUANTITIES`: whether it was finite
    finite: th.Tensor
    #: The step's entropy coefficient, critic loss, actor loss and, when it is learned, entropy coefficient loss
    logged: th.Tensor
    #: Each critic's learning rate after the step, ``(K,)``
    critic_rates: th.Tensor
    #: The step's SERA diagnostics (:func:`~sb3_sera.sera.update.diagnostics`; the last step's are logged)
    diagnostics: th.Tensor


def gradient_step(
    model: Any,
    replay_data: ReplayBufferSamples,
    *,
    learning_rates: th.Tensor,
    target_update: th.Tensor,
    healthy: th.Tensor,
    states: list[list[tuple[th.Tensor, th.Tensor, th.Tensor]]],
) -> CompiledStepOutput:
    """
    One gradient step of ``model`` (a :class:`~sb3_sera.sera.sera.SERASAC`, typed ``Any``: this module sits below
    it) as one graph, the body ``compile_update`` compiles.

    :param learning_rates: the actor's, the entropy coefficient's and the critics' scheduled rates, ``(3,)``
    :param target_update: whether the target critics are updated after this step, a boolean scalar tensor
    :param healthy: whether every earlier step of the ``train()`` call had only finite values
    :param states: each optimizer's Adam state (:meth:`.AdamPlan.state`), in ``model._adam_plans`` order
    """
    actor_plan, critic_plan = model._adam_plans[:2]
    actions_pi, log_prob = model.actor.action_log_prob(replay_data.observations)
    log_prob = log_prob.reshape(-1, 1)
    ent_coef = model._entropy_coefficient()
    critic = model._critic_update(replay_data, ent_coef)
    target_entropy, ent_coef_loss = model._entropy_target(critic.current_q_values, log_prob)
    critic_grads = th.autograd.grad(critic.critic_loss, critic_plan.parameters())
    finite = [
        th.isfinite(ent_coef).all(),
        th.isfinite(critic.target_q_values).all(),
        th.isfinite(critic.critic_loss),
        th.isfinite(ent_coef_loss) if ent_coef_loss is not None else healthy,
        th.isfinite(critic.step_size.learning_rates).all() if model.adaptive_critic_lr else healthy,
        all_finite(critic_grads),
    ]
    entropy_grads: tuple[th.Tensor, ...] = ()
    if ent_coef_loss is not None:
        entropy_grads = th.autograd.grad(ent_coef_loss, model._adam_plans[2].parameters())
    finite.append(all_finite(entropy_grads) if entropy_grads else healthy)
    apply = healthy & th.stack(finite).all()
    # Step size, entropy coefficient, critics: in train()'s order, each where every value so far was finite
    model.step_size.commit(critic.step_size, apply)
    scheduled = learning_rates[2]
    n_critics = model.critic.n_critics
    critic_rates = critic.step_size.learning_rates if model.adaptive_critic_lr else scheduled.expand(n_critics)
    if ent_coef_loss is not None:
        masked_adam(model._adam_plans[2], entropy_grads, states[2], [learning_rates[1]], apply)
    group_rates = [
        scheduled if group["critic_index"] is None else critic_rates[group["critic_index"]]
        for group in model.critic.parameter_groups()
    ]
    masked_adam(critic_plan, critic_grads, states[1], group_rates, apply)
    # The actor against the updated critics
    value = actor_value_linearized if model.device.type == "cpu" else actor_value_gathered
    q_value = value(model.critic, replay_data.observations, actions_pi, model.actor_aggregation)
    actor_loss = (ent_coef * log_prob - q_value).mean()
    actor_grads = th.autograd.grad(actor_loss, actor_plan.parameters())
    finite += [th.isfinite(actor_loss), all_finite(actor_grads)]
    apply_actor = apply & finite[-2] & finite[-1]
    masked_adam(actor_plan, actor_grads, states[0], [learning_rates[0]], apply_actor)
    masked_polyak(
        list(model.critic_target.parameters()), list(model.critic.parameters()), model.tau, apply_actor & target_update
    )
    masked_polyak(model.batch_norm_stats_target, model.batch_norm_stats, 1.0, apply_actor & target_update)
    logged = [ent_coef.reshape(()), critic.critic_loss.detach(), actor_loss.detach()]
    if ent_coef_loss is not None:
        logged.append(ent_coef_loss.detach())
    return CompiledStepOutput(
        healthy=apply_actor,
        finite=th.stack(finite),
        logged=th.stack(logged),
        critic_rates=critic_rates,
        diagnostics=diagnostics(critic, target_entropy),
    )


def train_compiled(model: Any, gradient_steps: int, batch_size: int) -> None:
    """
    ``model.train()``'s steps through its compiled :func:`gradient_step`: the same values, read from the device once,
    after the last step. A non-finite value raises ``FloatingPointError`` naming the first one; its step and those
    after it changed nothing.
    """
    sample = partial(model.replay_buffer.sample, batch_size, env=model._vec_normalize_env)
    outputs: list[CompiledStepOutput] = run_steps(model, sample, model._step_learning_rates(), gradient_steps)
    last = outputs[-1]
    logged, values = read_steps(
        outputs,
        COMPILED_QUANTITIES,
        partial(gradient_step_context, model),
        th.cat([last.critic_rates, last.diagnostics]),
    )
    n_critics = model.critic.n_critics
    critic_rates, step_diagnostics = values[:n_critics], values[n_critics:]
    if model.adaptive_critic_lr:
        model._update_critic_learning_rates(critic_rates)
    names = ["ent_coef", "critic_loss", "actor_loss", *(["ent_coef_loss"] if model.ent_coef_optimizer else [])]
    for name, value in zip(names, logged, strict=True):
        model.logger.record(f"train/{name}", value)
    model._end_train(gradient_steps, step_diagnostics, critic_rates)
