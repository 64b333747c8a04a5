"""
SERASAC's gradient step (the paper's Algorithm 2) as tensor functions of the networks and settings each needs: the
critic update, the entropy target, the actor's value of its actions and the diagnostics. The eager ``train()``
(:class:`~sb3_sera.sera.sera.SERASAC`) and the compiled step (``SERASAC._gradient_step_graph``) call the same
functions in the same order; only how the gradients are applied differs (torch's optimizers, or a masked Adam inside
one graph).
"""

from collections.abc import Callable
from typing import NamedTuple

import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs, ReplayBufferSamples
from stable_baselines3.sac.policies import Actor

from sb3_sera.sera.aggregation import (
    ActorAggregation,
    SERAOptions,
    TargetAggregation,
    aggregate_target,
    critic_correlation,
    ensemble_disagreement,
    median_anchor,
    selected_critic,
    td_error_correlation,
)
from sb3_sera.sera.policies import HeterogeneousCritics
from sb3_sera.sera.step_size import StepSizeUpdate, VarianceAdaptiveStepSize, batch_variance

#: The SERA diagnostics logged after each ``train()`` call (SPEC section 1), as ``train/<name>``
DIAGNOSTICS = (
    "td_target_var",
    "critic_disagreement",
    "target_entropy_eff",
    "q_sera_mean",
    "q_median_mean",
    "critic_corr",
    "td_error_corr",
)


class CriticUpdate(NamedTuple):
    """What one critic update computed (shapes for a batch of ``S`` samples and ``K`` critics)."""

    #: Target critics' values at the next state and action, ``(S, K)``
    next_q_values: th.Tensor
    #: Their aggregate, ``(S, 1)``
    next_q_aggregate: th.Tensor
    #: TD target ``y``, ``(S, 1)``
    target_q_values: th.Tensor
    #: Online critics' values at the replayed state and action, ``(S, K)``, with their graph
    current_q_values: th.Tensor
    #: Sum over critics of half the mean squared TD error
    critic_loss: th.Tensor
    #: Step-size statistics and rates, not yet committed
    step_size: StepSizeUpdate


def critic_update(
    actor: Actor,
    critic: HeterogeneousCritics,
    critic_target: HeterogeneousCritics,
    step_size: VarianceAdaptiveStepSize,
    replay_data: ReplayBufferSamples,
    ent_coef: th.Tensor,
    gamma: float,
    aggregation: TargetAggregation,
    options: SERAOptions,
) -> CriticUpdate:
    """
    The critic update on a batch (Algorithm 2, lines 5-16), computed, nothing changed yet: TD target from the
    aggregated target critics at next actions drawn from the current actor, the online critics' values and loss,
    and the step-size update (not yet committed). Critics without targets (``critic.target_free``) give the next
    values themselves, in the forward pass that gives the current ones.

    :param gamma: the discount factor (n-step batches carry their own discounts)
    :param aggregation: how the target critics' values form the target (:data:`~sb3_sera.sera.aggregation.TARGET_RULES`)
    :param options: the SERA target's settings
    """
    # For n-step replay, the discount factor is gamma**n_steps (when no early termination)
    discounts = replay_data.discounts if replay_data.discounts is not None else gamma
    with th.no_grad():
        next_actions, next_log_prob = actor.action_log_prob(replay_data.next_observations)
        next_log_prob = next_log_prob.reshape(-1, 1)
    if critic.target_free:
        # No target critics (CrossQ's recipe): the online critics read (s, a) and (s', a') in one forward pass, so
        # that both halves share the batch statistics of batch renormalization
        joint_q_values = critic.q_values(
            joined(replay_data.observations, replay_data.next_observations),
            th.cat([replay_data.actions, next_actions]),
        )
        current_q_values, next_q_values = joint_q_values.split(len(replay_data.actions))
        next_q_values = next_q_values.detach()
    else:
        with th.no_grad():
            # Target critics' values q_i(s', a'), shape (S, K)
            next_q_values = critic_target.q_values(replay_data.next_observations, next_actions)
        current_q_values = critic.q_values(replay_data.observations, replay_data.actions)
    with th.no_grad():
        # Aggregated to one target per sample
        next_q_aggregate = aggregate_target(next_q_values, aggregation, options).unsqueeze(1)
        next_q = next_q_aggregate - ent_coef * next_log_prob
        target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q
    # Each online critic regresses on the same target: delta_i = y - Q_i(s, a), shape (S, K)
    td_errors = target_q_values - current_q_values
    critic_loss = 0.5 * td_errors.pow(2).mean(dim=0).sum()
    # Variance-adaptive step size from detached tensors (stored by the caller once checked)
    update = step_size.compute(td_errors.detach(), next_q_values - next_q_aggregate)
    return CriticUpdate(
        next_q_values=next_q_values,
        next_q_aggregate=next_q_aggregate,
        target_q_values=target_q_values,
        current_q_values=current_q_values,
        critic_loss=critic_loss,
        step_size=update,
    )


def entropy_target(
    target_entropy: float,
    disagreement_coef: float,
    current_q_values: th.Tensor,
    log_prob: th.Tensor,
    log_ent_coef: th.Tensor | None,
) -> tuple[th.Tensor | float, th.Tensor | None]:
    """
    The disagreement-adjusted entropy target ``H_eff = H_target - beta * U`` at the replayed pairs, and the entropy
    coefficient's loss.

    :param target_entropy: ``H_target``
    :param disagreement_coef: ``beta`` (0: SAC's fixed target)
    :param current_q_values: the online critics' values at the replayed pairs, ``(S, K)``
    :param log_prob: the actor's log-probabilities of its actions at the replayed states, ``(S, 1)``
    :param log_ent_coef: the learned log entropy coefficient, None for a fixed coefficient (then no loss)
    """
    target: th.Tensor | float = target_entropy
    if disagreement_coef > 0:
        disagreement = ensemble_disagreement(current_q_values.detach()).unsqueeze(1)
        target = target_entropy - disagreement_coef * disagreement
    if log_ent_coef is None:
        return target, None
    return target, -(log_ent_coef * (log_prob + target).detach()).mean()


def joined(first: PyTorchObs, second: PyTorchObs) -> PyTorchObs:
    """Two batches of observations as one, ``first``'s rows then ``second``'s (key by key for ``Dict`` observations)."""
    if isinstance(first, dict):
        assert isinstance(second, dict)
        return {key: th.cat([first[key], second[key]]) for key in first}
    assert isinstance(second, th.Tensor)
    return th.cat([first, second])


def with_running_statistics(critic: HeterogeneousCritics, value: Callable[[], th.Tensor]) -> th.Tensor:
    """
    ``value()`` with the critics' batch renormalization layers (where there are any) in evaluation mode: the actor's
    loss reads the critics with their running statistics, as sb3-contrib's CrossQ does, and changes none of them.
    """
    mode = critic.bn_training_mode()
    critic.set_bn_training_mode(False)
    result = value()
    critic.set_bn_training_mode(mode)
    return result


def actor_value(
    critic: HeterogeneousCritics, observations: PyTorchObs, actions_pi: th.Tensor, aggregation: ActorAggregation
) -> th.Tensor:
    """
    The online critics' value of the actor's actions, aggregated by ``aggregation``, shape ``(S, 1)``; batch
    renormalization reads its running statistics (:func:`with_running_statistics`).

    For the median and the min only the selected critic carries a gradient, so all critics run without a graph to
    find it and only the selected one runs again, per sample, with a graph; critics with dropout run once
    (:func:`actor_value_gathered`), so that the critic is chosen and read under the same dropout mask.
    """
    if critic.norm.dropout_rate > 0:
        return actor_value_gathered(critic, observations, actions_pi, aggregation)

    def value() -> th.Tensor:
        q_input = critic.q_input(observations, actions_pi)
        if aggregation == "mean":
            return critic.q_values_from_input(q_input).mean(dim=1, keepdim=True)
        with th.no_grad():
            q_values = critic.q_values_from_input(q_input)
            index = selected_critic(q_values, aggregation)
        assert index is not None
        return critic.selected_q_values(q_input, index)

    return with_running_statistics(critic, value)


def actor_value_gathered(
    critic: HeterogeneousCritics, observations: PyTorchObs, actions_pi: th.Tensor, aggregation: ActorAggregation
) -> th.Tensor:
    """
    :func:`actor_value` with static shapes (the compiled step's: on a GPU, finding each critic's samples would
    synchronise with the device and keep CUDA graphs from replaying the step): every critic runs with a graph, the
    selected one's value is gathered.
    """
    q_values = with_running_statistics(critic, lambda: critic.q_values(observations, actions_pi))
    if aggregation == "mean":
        return q_values.mean(dim=1, keepdim=True)
    index = selected_critic(q_values.detach(), aggregation)
    assert index is not None
    return q_values.gather(1, index.unsqueeze(1))


def diagnostics(critic: CriticUpdate, target_entropy: th.Tensor | float) -> th.Tensor:
    """
    The SERA diagnostics of a gradient step (SPEC section 1) on the device, to be read in one transfer: the values of
    :data:`DIAGNOSTICS`, then each critic's ``kappa``, ``P`` and ``R`` in turn, shape ``(7 + 3K,)``.
    """
    with th.no_grad():
        current_q_values = critic.current_q_values.detach()
        device = current_q_values.device
        scalars = th.stack(
            [
                batch_variance(critic.target_q_values).squeeze(0),
                ensemble_disagreement(current_q_values).mean(),
                th.as_tensor(target_entropy, dtype=th.float32, device=device).mean(),
                critic.next_q_aggregate.mean(),
                median_anchor(critic.next_q_values)[0].mean(),
                critic_correlation(current_q_values),
                td_error_correlation(critic.target_q_values - current_q_values),
            ]
        )
        update = critic.step_size
        return th.cat([scalars, update.kappa, update.estimation_var, update.measurement_var])
