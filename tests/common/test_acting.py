"""The action ``learn()`` takes (:mod:`sb3_sera.common.acting`): SB3's ``predict`` less the checks ``learn()`` needs not."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_sera import IET, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.common.acting import acts_directly, drawing_actor, learn_action
from tests.helpers import CTDE_TASK, ENV_ID, SMALL, SMALL_CTDE


@pytest.mark.parametrize(
    ("algorithm", "policy", "env", "settings"),
    [
        (SERASAC, "MlpPolicy", ENV_ID, SMALL),
        (SUNRISE, "MlpPolicy", ENV_ID, dict(n_members=3, **SMALL)),
        (MASAC, "CTDEPolicy", CTDE_TASK, SMALL_CTDE),
        (MATD3, "CTDEPolicy", CTDE_TASK, SMALL_CTDE),
    ],
)
def test_the_learn_action_is_predicts_from_the_same_draws(algorithm, policy, env, settings):
    model = algorithm(policy, gym.make(env) if policy == "CTDEPolicy" else env, seed=0, **settings)
    assert model.env is not None and acts_directly(model.policy)
    observation = model.env.reset()
    model.policy.set_training_mode(True)
    th.manual_seed(3)
    direct = learn_action(model.policy, observation)
    assert not model.policy.training  # evaluation mode, as predict sets it
    th.manual_seed(3)
    expected, _ = model.policy.predict(observation, deterministic=False)
    np.testing.assert_array_equal(direct, expected)
    # learn() takes it, model.predict stays SB3's (a single observation, deterministic)
    model.learn(settings["learning_starts"] + 3)
    single = {key: value[0] for key, value in observation.items()} if isinstance(observation, dict) else observation[0]
    assert model.predict(single, deterministic=True)[0].shape == model.action_space.shape


def test_sacs_draw_without_its_distribution_is_the_same_and_a_nan_gets_sb3s_error():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL)
    assert drawing_actor(model.policy) is model.actor  # the draw above was this one: SB3's SAC actor
    assert drawing_actor(MATD3("CTDEPolicy", gym.make(CTDE_TASK), **SMALL_CTDE).policy) is None
    with th.no_grad():
        model.actor.mu.weight.fill_(np.nan)
    observation = model.env.reset()
    with pytest.raises(ValueError, match="Expected parameter loc"):
        model.policy.predict(observation, deterministic=False)
    with pytest.raises(ValueError, match="Expected parameter loc"):
        learn_action(model.policy, observation)


def test_policies_with_their_own_predict_or_images_act_through_predict():
    iet = IET("CTDEPolicy", gym.make(CTDE_TASK), seed=0, **SMALL_CTDE)
    assert not acts_directly(iet.policy)  # IET's policy draws its latents in its own predict
    image = spaces.Box(0, 255, (36, 36, 3), dtype=np.uint8)
    assert not acts_directly(SERASAC("CnnPolicy", _ImageEnv(image), buffer_size=10).policy)


class _ImageEnv(gym.Env):
    """An env of image observations (SB3's predict transposes those): only its spaces are read."""

    def __init__(self, observation_space: spaces.Box):
        self.observation_space = observation_space
        self.action_space = spaces.Box(-1, 1, (1,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}
