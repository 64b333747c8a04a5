"""SB3 SAC's TD target on hand-computed numbers, with the batch's own discounts (an n-step buffer's) and without."""

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_sera.common.targets import sac_td_target


class _Actor:
    """Draws the next action 0.5 everywhere, with log-probability -1."""

    def action_log_prob(self, observations: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        return th.full((len(observations), 1), 0.5), th.full((len(observations),), -1.0)


def _critic_target(observations: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    # Two target critics: the next state's value and 1 more; the minimum is the first
    return observations, observations + 1.0


def _batch(discounts: th.Tensor | None) -> ReplayBufferSamples:
    return ReplayBufferSamples(
        observations=th.zeros(2, 1),
        actions=th.zeros(2, 1),
        next_observations=th.tensor([[2.0], [4.0]]),
        dones=th.tensor([[0.0], [1.0]]),
        rewards=th.tensor([[1.0], [3.0]]),
        discounts=discounts,
    )


def test_the_sac_target_discounts_with_the_batch_s_discounts_where_it_has_them():
    ent_coef = th.tensor(0.5)
    # min_k Qbar(s', a') - alpha log pi = 2 + 0.5 = 2.5 for the first transition; the second is terminal
    assert th.allclose(sac_td_target(_Actor(), _critic_target, _batch(None), ent_coef, 0.9), th.tensor([[3.25], [3.0]]))
    three_steps = th.tensor([[0.729], [0.729]])
    expected = th.tensor([[1.0 + 0.729 * 2.5], [3.0]])
    assert th.allclose(sac_td_target(_Actor(), _critic_target, _batch(three_steps), ent_coef, 0.9), expected)
