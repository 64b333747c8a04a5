"""SB3 SAC's TD target, one function for every place that computes it (MASAC's compiled step, the critic diagnostics)."""

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.sac.policies import Actor
from torch import nn


def sac_td_target(
    actor: Actor, critic_target: nn.Module, replay_data: ReplayBufferSamples, ent_coef: th.Tensor, gamma: float
) -> th.Tensor:
    """
    SB3's SAC target for a replayed batch, ``y = r + discount (1 - d) (min_k Qbar_k(s', a') - alpha log pi(a'|s'))``,
    with ``a'`` drawn from the actor and ``discount`` the batch's own where the replay buffer gives one (an n-step
    buffer's ``gamma ** n``, per transition), else ``gamma``. Computes no gradient; shape ``(S, 1)``.
    """
    discounts = replay_data.discounts if replay_data.discounts is not None else gamma
    with th.no_grad():
        next_actions, next_log_prob = actor.action_log_prob(replay_data.next_observations)
        next_q_values = th.cat(critic_target(replay_data.next_observations, next_actions), dim=1)
        next_q = th.min(next_q_values, dim=1, keepdim=True).values - ent_coef * next_log_prob.reshape(-1, 1)
        return replay_data.rewards + (1 - replay_data.dones) * discounts * next_q
