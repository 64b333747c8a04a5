"""
ACE's look-ahead tree (Zhang, Chen & Yao, AAAI 2019, section 3) as functions of tensors and of the networks' calls.

With a state feature ``phi``, actor heads ``mu_k``, a critic ``Q`` and learned models of the reward ``r_hat`` and of
the next feature ``phi_hat'``, the value of an action looked ``d`` steps ahead is

``Q_1(phi, a) = Q(phi, a)``,
``Q_d(phi, a) = r_hat(phi, a) + gamma * max_k Q_{d-1}(phi_hat'(phi, a), mu_k(phi_hat'(phi, a)))`` for ``d > 1``,

and a state's value is the best of its actor heads, ``V_d(phi) = max_k Q_d(phi, mu_k(phi))``. The heads' proposals
inside the tree are constants (detached), as in the authors' code: the tree trains the critic and the models only.
"""

from collections.abc import Callable
from typing import NamedTuple

import torch as th

#: ``Q(phi, a)``: features ``(..., F)`` and actions ``(..., A)`` to values ``(..., 1)``
Critic = Callable[[th.Tensor, th.Tensor], th.Tensor]
#: ``(phi_hat', r_hat)`` for features ``(..., F)`` and actions ``(..., A)``: ``(..., F)`` and ``(..., 1)``
EnvModel = Callable[[th.Tensor, th.Tensor], tuple[th.Tensor, th.Tensor]]
#: Every head's action for features ``(..., F)``: ``(..., K, A)``
Actors = Callable[[th.Tensor], th.Tensor]


class TreeValue(NamedTuple):
    """The look-ahead value of an action and, for depth > 1, the parts it was made of."""

    #: ``Q_d(phi, a)``, ``(..., 1)``
    q_value: th.Tensor
    #: ``r_hat(phi, a)`` (None at depth 1), ``(..., 1)``
    reward: th.Tensor | None
    #: ``max_k Q_{d-1}(phi_hat', mu_k(phi_hat'))`` (None at depth 1), ``(..., 1)``
    next_value: th.Tensor | None


def tree_value(
    phi: th.Tensor, actions: th.Tensor, depth: int, gamma: float, critic: Critic, env_model: EnvModel, actors: Actors
) -> TreeValue:
    """
    ``Q_d(phi, a)`` for features ``(..., F)`` and actions ``(..., A)``.

    :param depth: ``d >= 1`` (1: the critic alone)
    :param gamma: discount of the reward model's steps
    """
    if depth < 1:
        raise ValueError(f"depth={depth} is invalid: expected an integer >= 1")
    if depth == 1:
        return TreeValue(critic(phi, actions), None, None)
    next_phi, reward = env_model(phi, actions)
    next_value = state_value(next_phi, depth - 1, gamma, critic, env_model, lambda f: actors(f).detach())
    return TreeValue(reward + gamma * next_value, reward, next_value)


def head_values(
    phi: th.Tensor, depth: int, gamma: float, critic: Critic, env_model: EnvModel, actors: Actors
) -> tuple[th.Tensor, th.Tensor]:
    """
    Every head's proposal and its look-ahead value.

    :return: the proposals ``(..., K, A)`` and ``Q_d(phi, mu_k(phi))``, ``(..., K)``
    """
    proposals = actors(phi)
    expanded = phi.unsqueeze(-2).expand(*phi.shape[:-1], proposals.shape[-2], phi.shape[-1])
    return proposals, tree_value(expanded, proposals, depth, gamma, critic, env_model, actors).q_value.squeeze(-1)


def state_value(phi: th.Tensor, depth: int, gamma: float, critic: Critic, env_model: EnvModel, actors: Actors) -> th.Tensor:
    """``V_d(phi) = max_k Q_d(phi, mu_k(phi))``, ``(..., 1)``."""
    return head_values(phi, depth, gamma, critic, env_model, actors)[1].max(dim=-1, keepdim=True).values


def best_actions(proposals: th.Tensor, values: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """
    The proposal of the head with the highest look-ahead value, per sample.

    :param proposals: ``(S, K, A)``
    :param values: ``(S, K)``
    :return: the actions ``(S, A)`` and the chosen heads ``(S,)``
    """
    heads = values.argmax(dim=-1)
    return proposals[th.arange(proposals.shape[0], device=proposals.device), heads], heads
