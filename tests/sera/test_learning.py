"""Long learning checks, kept out of CI (`make test-slow`)."""

import pytest
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_sera import SERASAC


@pytest.mark.slow
def test_serasac_solves_pendulum():
    model = SERASAC("MlpPolicy", "Pendulum-v1", seed=0, learning_rate=1e-3, critic_lr_max=1e-3).learn(8_000)
    mean_return, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=5)
    # A random policy scores about -1200; a solved pendulum, above -200
    assert mean_return > -400
