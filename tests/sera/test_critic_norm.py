"""
SERASAC's normalized critics: DroQ's (LayerNorm and dropout) and CrossQ's (batch renormalization, no target critics),
their layers and numbers, the target-free update, save/load, the multi-agent policy and the errors.
"""

import numpy as np
import pytest
import torch as th
from sb3_contrib.common.torch_layers import BatchRenorm1d
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import set_random_seed
from torch import nn

from sb3_sera import MASAC, SERASAC
from sb3_sera.common.normalization import BatchRenorm
from sb3_sera.sera.aggregation import aggregate_target
from tests.helpers import CTDE_TASK, ENV_ID, SMALL, SMALL_CTDE, assert_same_state, snapshot

DROQ = dict(layer_norm=True, dropout_rate=0.01)
CROSSQ = dict(batch_norm=True)


def build(critic_kwargs: dict, seed: int = 0, **kwargs) -> SERASAC:
    policy_kwargs = dict(n_critics=3, critic_archs=[[16], [16, 16], [24]], net_arch=[16], **critic_kwargs)
    return SERASAC("MlpPolicy", ENV_ID, seed=seed, policy_kwargs=policy_kwargs, **{**SMALL, **kwargs})


def test_batch_renorm_normalizes_a_batch_by_hand_then_renormalizes_as_sb3_contrib_does():
    layer = BatchRenorm(2, momentum=0.5, eps=0.0, warmup_steps=1)
    batch = th.tensor([[1.0, 10.0], [3.0, 10.0], [5.0, 16.0]])
    # Warm-up: batch normalization (mean 3 and 12, unbiased variance 4 and 12), the running statistics moved halfway
    np.testing.assert_allclose(layer(batch).detach(), [[-1.0, -1 / 3**0.5], [0.0, -1 / 3**0.5], [1.0, 2 / 3**0.5]], rtol=1e-6)
    np.testing.assert_allclose(layer.ra_mean, [1.5, 6.0])
    np.testing.assert_allclose(layer.ra_var, [2.5, 6.5])
    assert layer.steps == 1
    # After the warm-up and in evaluation mode: sb3-contrib's layer, with the same state, gives the same numbers
    reference = BatchRenorm1d(2, momentum=0.5, eps=1e-3, warmup_steps=1)
    layer.eps = 1e-3
    for step in range(3):
        reference.load_state_dict(layer.state_dict())
        shifted = batch * (step + 1) + step
        np.testing.assert_allclose(layer(shifted).detach(), reference(shifted).detach(), rtol=1e-6)
        np.testing.assert_allclose(layer.ra_var, reference.ra_var, rtol=1e-6)
    layer.eval()
    reference.eval()
    np.testing.assert_allclose(layer(batch).detach(), reference(batch).detach(), rtol=1e-6)


def test_droq_and_crossq_critics_have_their_layers_in_sbx_and_sb3_contribs_order():
    droq, crossq = build(DROQ).critic, build(CROSSQ).critic
    assert [type(layer) for layer in droq.qf1] == [nn.Linear, nn.Dropout, nn.LayerNorm, nn.ReLU] * 2 + [nn.Linear]
    assert droq.qf1[1].p == 0.01 and not droq.target_free
    assert [type(layer) for layer in crossq.qf1] == [BatchRenorm, nn.Linear, nn.ReLU] * 2 + [BatchRenorm, nn.Linear]
    assert crossq.qf0[0].momentum == 0.01 and crossq.qf0[0].warmup_steps == 100_000 and crossq.target_free


def test_batch_renormalized_critics_are_their_own_targets_and_never_polyak_averaged():
    model = build(CROSSQ, tau=0.5).learn(SMALL["learning_starts"] + 20)
    assert model.critic_target is model.critic and model.policy.critic_target is model.policy.critic
    before = snapshot(model)
    model._target_step(0)
    assert_same_state(before, snapshot(model))
    # One forward pass in training mode a gradient step: the actor reads the running statistics, changing none
    assert all(int(layer.steps) == model._n_updates for layer in model.critic._renorm_layers)


def test_the_target_free_td_target_comes_from_the_joint_forward_pass():
    model = build(CROSSQ, ent_coef=0.2).learn(SMALL["learning_starts"] + 20)
    model.policy.set_training_mode(True)
    data = model.replay_buffer.sample(32)
    set_random_seed(5)
    target, current = model.td_targets(data)
    set_random_seed(5)
    with th.no_grad():
        next_actions, next_log_prob = model.actor.action_log_prob(data.next_observations)
        joint = model.critic.q_values(
            th.cat([data.observations, data.next_observations]), th.cat([data.actions, next_actions])
        )
    next_value = aggregate_target(joint[32:], "sera", model.sera_options).unsqueeze(1) - 0.2 * next_log_prob.reshape(-1, 1)
    expected = data.rewards + (1 - data.dones) * model.gamma * next_value
    np.testing.assert_allclose(target, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(current.detach(), joint[:32], rtol=1e-5, atol=1e-5)


def test_dropout_is_on_while_training_and_off_when_evaluating():
    model = build(dict(dropout_rate=0.5)).learn(SMALL["learning_starts"] + 5)
    observations = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(8)]))
    actions = th.zeros(8, 1)
    model.policy.set_training_mode(True)
    assert not th.equal(model.critic.q_values(observations, actions), model.critic.q_values(observations, actions))
    model.policy.set_training_mode(False)
    assert th.equal(model.critic.q_values(observations, actions), model.critic.q_values(observations, actions))
    # The target critics stay in evaluation mode, as SB3's
    assert not model.critic_target.qf0[1].training


@pytest.mark.parametrize("critic_kwargs", [DROQ, CROSSQ], ids=["droq", "crossq"])
def test_normalized_critics_save_load_and_go_on(critic_kwargs, tmp_path):
    model = build(critic_kwargs).learn(SMALL["learning_starts"] + 30)
    observations = np.stack([model.observation_space.sample() for _ in range(8)])
    model.save(tmp_path / "model")
    loaded = SERASAC.load(tmp_path / "model", env=make_vec_env(ENV_ID, n_envs=1))
    for key, value in critic_kwargs.items():
        assert loaded.policy.critic_norm.kwargs()[key] == value
    assert_same_state(snapshot(model), snapshot(loaded))
    np.testing.assert_array_equal(
        model.predict(observations, deterministic=True)[0], loaded.predict(observations, deterministic=True)[0]
    )
    assert (loaded.critic_target is loaded.critic) == model.critic.target_free
    loaded.learn(20, reset_num_timesteps=False)
    assert loaded._n_updates == model._n_updates + 20


@pytest.mark.parametrize("critic_kwargs", [DROQ, CROSSQ], ids=["droq", "crossq"])
def test_normalized_critics_train_a_multi_agent_task(critic_kwargs):
    model = SERASAC("CTDEPolicy", CTDE_TASK, seed=0, policy_kwargs=dict(net_arch=[16], **critic_kwargs), **SMALL_CTDE)
    model.learn(SMALL_CTDE["learning_starts"] + 20)
    assert model._n_updates == 20 and np.isfinite(model.logger.name_to_value["train/critic_loss"])
    assert (model.critic_target is model.critic) == critic_kwargs.get("batch_norm", False)


@pytest.mark.parametrize(
    ("critic_kwargs", "message"),
    [
        (dict(dropout_rate=1.0), r"dropout_rate=1\.0 is out of range: allowed \[0\.0, 1\.0\)"),
        (dict(dropout_rate=-0.1), "dropout_rate=-0.1 is out of range"),
        (dict(layer_norm="yes"), "layer_norm='yes' is invalid: expected one of True, False"),
        (dict(batch_norm_momentum=0.0), r"batch_norm_momentum=0\.0 is out of range: allowed \(0\.0, 1\.0\]"),
        (dict(batch_norm_eps=0.0), "batch_norm_eps=0.0 is out of range"),
        (dict(renorm_warmup_steps=-1), "renorm_warmup_steps=-1 is out of range: allowed an integer >= 0"),
        (dict(batch_norm=True, layer_norm=True), "choose one recipe"),
        (dict(batch_norm=True, dropout_rate=0.01), "choose one recipe"),
    ],
)
def test_invalid_critic_norms_are_named(critic_kwargs, message):
    with pytest.raises(ValueError, match=message):
        build(critic_kwargs)


def test_masac_takes_droqs_critics_and_saves_and_loads_them(tmp_path):
    model = MASAC("CTDEPolicy", CTDE_TASK, seed=0, policy_kwargs=dict(net_arch=[16], **DROQ), **SMALL_CTDE)
    assert [type(layer) for layer in model.critic.qf1] == [nn.Linear, nn.Dropout, nn.LayerNorm, nn.ReLU, nn.Linear]
    assert [type(layer) for layer in model.critic_target.qf0] == [type(layer) for layer in model.critic.qf0]
    model.learn(SMALL_CTDE["learning_starts"] + 10)
    model.save(tmp_path / "model")
    loaded = MASAC.load(tmp_path / "model")
    assert loaded.policy.critic_norm == model.policy.critic_norm
    assert_same_state(snapshot(model), snapshot(loaded))


def test_masac_refuses_batch_norm_and_names_serasacs_equivalent():
    with pytest.raises(ValueError, match=r"SERASAC\('CTDEPolicy', env, policy_kwargs=dict\(n_critics=2"):
        MASAC("CTDEPolicy", CTDE_TASK, policy_kwargs=dict(batch_norm=True))
