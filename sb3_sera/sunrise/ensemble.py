"""
The math of SUNRISE (docs/SPEC.md, section 4) as pure functions of tensors with a leading member dimension.

Shapes: ``N`` members, ``C`` critics per member (twin critics: ``C = 2``), ``S`` samples, ``A`` action dimensions.
Every function treats the members independently (or, for the ensemble statistics, reduces over them explicitly), so
the batched update equals a loop over members and each function can be checked on hand-computed numbers.
"""

import math

import torch as th

#: Added inside the log of the tanh correction of the squashed Gaussian's log-probability, as SB3's SAC does
TANH_LOG_EPS = 1e-6


def ensemble_std(q_values: th.Tensor) -> th.Tensor:
    """
    Standard deviation over every critic of every member, per sample: the population standard deviation (divided
    by the number of values, as the authors' code computes it) over all ``N * C`` values.

    :param q_values: critic values, shape ``(N, C, S)``
    :return: ``std_Q``, shape ``(S,)``
    """
    return th.std(q_values.flatten(0, 1), dim=0, correction=0)


def backup_weight(std_q: th.Tensor, temperature: float) -> th.Tensor:
    """
    Weight of a sample's Bellman backup, ``w = sigmoid(-std_Q * T) + 0.5``, in ``[0.5, 1]``: 1 where the target
    critics agree, towards 0.5 where they disagree.

    :param std_q: ensemble standard deviation of the target values, any shape
    :param temperature: ``T >= 0`` (0: every weight is 1)
    :return: the weights, shape of ``std_q``
    """
    return th.sigmoid(-std_q * temperature) + 0.5


def masked_mean(values: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Each member's mean over the samples its bootstrap mask keeps, ``sum(mask * x) / (sum(mask) + 1)`` (the authors'
    normalisation: the ``+ 1`` keeps a member with an empty mask at zero loss).

    :param values: per-member, per-sample values, shape ``(N, S)``
    :param masks: bootstrap masks (0 or 1), shape ``(N, S)``
    :return: one mean per member, shape ``(N,)``
    """
    return (values * masks).sum(dim=-1) / (masks.sum(dim=-1) + 1)


def weighted_bellman_loss(current_q: th.Tensor, target_q: th.Tensor, weights: th.Tensor, masks: th.Tensor) -> th.Tensor:
    """
    Each member's weighted, masked squared TD error, summed over its critics:
    ``sum_c sum_s w_s * mask_s * (Q_c(s, a) - y_s)^2 / (sum_s mask_s + 1)``.

    :param current_q: online critics' values at the replayed state-action pairs, shape ``(N, C, S)``
    :param target_q: each member's TD target ``y``, shape ``(N, S)``
    :param weights: backup weights :func:`backup_weight`, shared by the members, shape ``(S,)``
    :param masks: bootstrap masks, shape ``(N, S)``
    :return: one loss per member, shape ``(N,)``
    """
    squared_errors = (current_q - target_q.unsqueeze(1)).pow(2).sum(dim=1)
    return masked_mean(weights * squared_errors, masks)


def ucb_choice(q_values: th.Tensor, ucb_lambda: float) -> th.Tensor:
    """
    Index of the proposal with the highest upper confidence bound ``mean_Q + lambda * std_Q``, mean and (population)
    standard deviation over every critic of the ensemble; ties go to the first proposal.

    :param q_values: every critic's value of every proposed action, shape ``(n_critics, n_proposals, S)``
    :param ucb_lambda: weight ``lambda >= 0`` of the standard deviation
    :return: the chosen proposal per sample, shape ``(S,)``
    """
    scores = q_values.mean(dim=0) + ucb_lambda * th.std(q_values, dim=0, correction=0)
    return th.argmax(scores, dim=0)


def squashed_gaussian_sample(mean: th.Tensor, log_std: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """
    Reparameterized sample of ``tanh(u)``, ``u ~ N(mean, exp(log_std)^2)``, and its log-probability with the tanh
    correction (SB3's ``SquashedDiagGaussianDistribution``, over the last dimension).

    :param mean: Gaussian means, shape ``(..., A)``
    :param log_std: Gaussian log standard deviations, shape ``(..., A)``
    :return: actions in ``(-1, 1)``, shape ``(..., A)``, and their log-probabilities, shape ``(...)``
    """
    noise = th.randn_like(mean)
    gaussian_actions = mean + log_std.exp() * noise
    actions = th.tanh(gaussian_actions)
    gaussian_log_prob = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_prob = gaussian_log_prob.sum(dim=-1) - th.log(1 - actions.pow(2) + TANH_LOG_EPS).sum(dim=-1)
    return actions, log_prob
