"""SERASAC as an SB3 algorithm: training, the per-critic step size, SAC equivalence, save/load, errors."""

import copy
import itertools

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch._dynamo.utils import counters

from sb3_sera import SERASAC
from sb3_sera.common.compiled import compile_step
from sb3_sera.sera import PAPER_RATES
from sb3_sera.sera.policies import CRITIC_ARCHS, HeterogeneousCritics
from sb3_sera.sera.update import actor_value, actor_value_gathered
from tests.helpers import ENV_ID, SMALL, assert_same_state, serasac_as_sac, snapshot


def linear_shapes(module: th.nn.Module) -> list[tuple[int, int]]:
    return [(layer.in_features, layer.out_features) for layer in module.modules() if isinstance(layer, th.nn.Linear)]


def test_default_critics_follow_table_4():
    model = SERASAC("MlpPolicy", ENV_ID, **SMALL)
    in_dim = 3 + 1  # Pendulum: 3 observations + 1 action
    assert model.critic.n_critics == 5
    for q_net, arch in zip(model.critic.q_networks, CRITIC_ARCHS, strict=True):
        sizes = [in_dim, *arch, 1]
        assert linear_shapes(q_net) == list(itertools.pairwise(sizes))
    # Target critics start as copies of the online critics
    for online, target in zip(model.critic.parameters(), model.critic_target.parameters(), strict=True):
        assert th.equal(online, target)


def test_critics_with_equal_archs_have_their_own_initialization():
    model = SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(n_critics=6), **SMALL)
    assert linear_shapes(model.critic.q_networks[0]) == linear_shapes(model.critic.q_networks[5])
    assert not th.equal(model.critic.q_networks[0][0].weight, model.critic.q_networks[5][0].weight)


def test_user_archs_and_homogeneous_net_arch():
    model = SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(n_critics=3, critic_archs=[[8], [16, 8], [4, 4, 4]]), **SMALL)
    assert [linear_shapes(q)[0][1] for q in model.critic.q_networks] == [8, 16, 4]
    model = SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(n_critics=3, net_arch=[32, 32]), **SMALL)
    assert all(linear_shapes(q) == [(4, 32), (32, 32), (32, 1)] for q in model.critic.q_networks)
    assert linear_shapes(model.actor.latent_pi) == [(3, 32), (32, 32)]
    # An actor-only net_arch keeps the Table 4 critics
    model = SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(net_arch=dict(pi=[16])), **SMALL)
    assert linear_shapes(model.actor.latent_pi) == [(3, 16)]
    assert [linear_shapes(q)[0][1] for q in model.critic.q_networks] == [256, 128, 256, 512, 128]


def test_one_parameter_group_per_critic():
    model = SERASAC("MlpPolicy", ENV_ID, **SMALL)
    groups = model.critic.optimizer.param_groups
    assert [group["critic_index"] for group in groups] == [0, 1, 2, 3, 4]
    for group, q_net in zip(groups, model.critic.q_networks, strict=True):
        assert [id(p) for p in group["params"]] == [id(p) for p in q_net.parameters()]


def test_the_selected_critic_runs_on_its_samples_alone_eagerly_and_compiled():
    # The actor's value under the median or min aggregation: each sample's selected critic, with its gradient, found
    # without reading the device, so that the compiled step on a CPU traces it (data-dependent sizes in one graph)
    critic = SERASAC("MlpPolicy", ENV_ID, **SMALL).critic
    q_input = th.randn(12, 4, requires_grad=True)
    index = th.tensor([0, 2, 2, 4, 0, 1, 2, 0, 4, 4, 2, 0])  # critic 3 is selected by no sample
    gathered = critic.q_values_from_input(q_input).gather(1, index.unsqueeze(1))
    (gathered_grad,) = th.autograd.grad(gathered.sum(), q_input)

    def selected(inputs: th.Tensor, critic_index: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        values = critic.selected_q_values(inputs, critic_index)
        return values.detach(), th.autograd.grad(values.sum(), inputs)[0]

    compiled = compile_step(selected, True)
    for run in (selected, compiled):
        values, grad = run(q_input, index)
        th.testing.assert_close(values, gathered)
        th.testing.assert_close(grad, gathered_grad)
    # Other counts per critic reuse the graph
    graphs = counters["stats"]["unique_graphs"]
    values, _ = compiled(q_input, th.arange(12) % 5)
    th.testing.assert_close(values, critic.q_values_from_input(q_input).gather(1, (th.arange(12) % 5).unsqueeze(1)))
    assert counters["stats"]["unique_graphs"] == graphs


def ensemble() -> HeterogeneousCritics:
    """Three critics on 5 observations and 3 actions (the action is the last 3 columns of their input)."""
    observation_space = spaces.Box(-1, 1, (5,))
    return HeterogeneousCritics(
        observation_space,
        spaces.Box(-1, 1, (3,)),
        critic_archs=[[16, 8], [8], [4, 4, 4]],
        features_extractor=FlattenExtractor(observation_space),
        features_dim=5,
    )


@pytest.mark.parametrize("aggregation", ["median", "min", "mean"])
def test_the_gathered_actor_value_has_the_actor_values_value_and_gradient(aggregation):
    # The compiled step's actor value: every critic run, the selected one's value gathered (static shapes), the same
    # value and the same gradient to the actions as actor_value (each critic on its own samples), eagerly and compiled
    th.manual_seed(0)
    critic = ensemble()
    observations, actions = th.randn(40, 5), th.rand(40, 3, requires_grad=True)
    reference = actor_value(critic, observations, actions, aggregation)
    (reference_grad,) = th.autograd.grad(reference.sum(), actions)

    def gathered(obs: th.Tensor, acts: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        value = actor_value_gathered(critic, obs, acts, aggregation)
        return value.detach(), th.autograd.grad(value.sum(), acts)[0]

    for run in (gathered, compile_step(gathered, True)):
        value, grad = run(observations, actions)
        th.testing.assert_close(value, reference.detach())
        th.testing.assert_close(grad, reference_grad)


class CountedTrain(th.nn.Module):
    """A module that overrides ``train`` (as a user's module may, to keep a part frozen)."""

    def __init__(self) -> None:
        super().__init__()
        self.inner = th.nn.Dropout()
        self.calls: list[bool] = []

    def train(self, mode: bool = True) -> "CountedTrain":
        self.calls.append(mode)
        self.training = mode
        self.inner.train(False)  # kept in evaluation mode
        return self


def test_set_training_mode_sets_the_actor_and_the_critics_as_module_train_does():
    policy = SERASAC("MlpPolicy", ENV_ID, **SMALL).policy
    custom = CountedTrain()
    policy.critic.qf2.append(custom)
    for mode in (False, True, False):
        policy.set_training_mode(mode)
        assert policy.training is mode
        assert all(module.training is mode for module in policy.actor.modules())
        assert all(module.training is mode for module in policy.critic.modules() if module is not custom.inner)
        # The target critics stay in evaluation mode, as in SB3's SAC policy
        assert not any(module.training for module in policy.critic_target.modules())
    assert custom.calls == [False, True, False] and not custom.inner.training
    with pytest.raises(ValueError, match="boolean"):
        policy.set_training_mode(1)  # type: ignore[arg-type]


def test_learn_logs_diagnostics():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(200)
    logged = model.logger.name_to_value
    for key in ("td_target_var", "critic_disagreement", "target_entropy_eff", "q_sera_mean", "q_median_mean", "critic_corr"):
        assert np.isfinite(logged[f"train/{key}"]), key
    for index in range(5):
        for prefix in ("kappa", "critic_lr", "P", "R"):
            assert f"train/{prefix}_{index}" in logged
    assert logged["train/critic_disagreement"] > 0
    assert -1.0 <= logged["train/critic_corr"] <= 1.0


@pytest.mark.parametrize(
    "rates, lr_max, actor_lr",
    [({}, 1e-3, 1e-3), (PAPER_RATES, 5e-4, 3e-4)],
    ids=["defaults", "paper"],
)
def test_adaptive_learning_rate_is_the_optimizer_step_size(rates, lr_max, actor_lr):
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **rates, **SMALL)
    model.learn(SMALL["learning_starts"])  # fills the buffer, no gradient step yet
    before = [[p.detach().clone() for p in q.parameters()] for q in model.critic.q_networks]
    model.train(gradient_steps=1, batch_size=32)
    logged = model.logger.name_to_value
    rates = [logged[f"train/critic_lr_{i}"] for i in range(5)]
    for i, rate in enumerate(rates):
        # SB3's learning-rate update ran first (the actor's rate everywhere), then each critic got its own rate
        assert model.critic.optimizer.param_groups[i]["lr"] == rate
        assert rate == pytest.approx(lr_max * (0.2 + 0.8 * logged[f"train/kappa_{i}"]), rel=1e-5)
        assert 0.2 * lr_max <= rate <= lr_max
        # Adam's first step moves each weight by about the learning rate: the rate is a real step size,
        # not a loss scale (which Adam would cancel)
        largest_move = max(
            (p - b).abs().max().item() for p, b in zip(model.critic.q_networks[i].parameters(), before[i], strict=True)
        )
        assert largest_move == pytest.approx(rate, rel=1e-3)
    assert len(set(rates)) > 1
    assert model.actor.optimizer.param_groups[0]["lr"] == actor_lr


def test_fixed_critic_learning_rate_follows_schedule():
    model = SERASAC("MlpPolicy", ENV_ID, adaptive_critic_lr=False, critic_learning_rate=1e-3, **SMALL).learn(100)
    assert all(group["lr"] == 1e-3 for group in model.critic.optimizer.param_groups)
    assert model.logger.name_to_value["train/critic_lr_0"] == 1e-3


def test_entropy_target_is_adjusted_by_disagreement():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, disagreement_coef=0.5, **SMALL).learn(150)
    logged = model.logger.name_to_value
    expected = model.target_entropy - 0.5 * logged["train/critic_disagreement"]
    assert logged["train/target_entropy_eff"] == pytest.approx(expected, rel=1e-5)
    assert model.target_entropy == -1.0
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, disagreement_coef=0.0, **SMALL).learn(150)
    assert model.logger.name_to_value["train/target_entropy_eff"] == -1.0


@pytest.fixture(scope="module")
def default_trained() -> dict[str, th.Tensor]:
    """What SERASAC with its defaults learns in the variants' budget and seed."""
    return snapshot(SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(VARIANT_STEPS))


#: The variants' budget: 70 gradient steps after SMALL's learning_starts
VARIANT_STEPS = 120


@pytest.mark.parametrize(
    ("kwargs", "effect"),
    [
        (dict(target_aggregation="mean"), None),
        (dict(target_aggregation="median"), None),
        (dict(target_aggregation="min"), None),
        (dict(sera_include_median=True), None),
        (dict(sera_temperature_mode="relative"), None),
        (dict(actor_aggregation="mean"), None),
        (dict(actor_aggregation="min"), None),
        (
            dict(adaptive_critic_lr=False),
            lambda model, logged: {logged[f"train/critic_lr_{i}"] for i in range(5)} == {model.learning_rate},
        ),
        (
            dict(ent_coef=0.1),
            lambda model, logged: logged["train/ent_coef"] == pytest.approx(0.1) and model.ent_coef_optimizer is None,
        ),
        (dict(n_steps=3), lambda model, logged: type(model.replay_buffer).__name__ == "NStepReplayBuffer"),
        (
            dict(policy_kwargs=dict(n_critics=4)),
            lambda model, logged: "train/critic_lr_4" not in logged and model.critic.n_critics == 4,
        ),
        (dict(use_sde=True), lambda model, logged: model.actor.use_sde),
    ],
)
def test_variants_train_and_take_effect(kwargs, effect, default_trained):
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **{**SMALL, **kwargs}).learn(VARIANT_STEPS)
    logged = model.logger.name_to_value
    assert np.isfinite(logged["train/critic_loss"])
    # An option ignored would leave training bit for bit the default's (same seed, one thread)
    trained = snapshot(model)
    assert trained.keys() != default_trained.keys() or any(not th.equal(trained[k], default_trained[k]) for k in trained)
    assert effect is None or effect(model, logged)


def test_a_shared_features_extractor_is_the_actors():
    # With MlpPolicy's extractor (a flatten, no parameters) sharing it changes no number: shown by identity instead
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, policy_kwargs=dict(share_features_extractor=True), **SMALL).learn(60)
    assert model.critic.features_extractor is model.actor.features_extractor
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])
    default = SERASAC("MlpPolicy", ENV_ID, **SMALL)
    assert default.critic.features_extractor is not default.actor.features_extractor


def test_sac_equivalent_configuration():
    """n_critics=2, [256, 256] critics, min target and actor, fixed lr, beta=0: SB3 SAC's losses and updates."""
    env = make_vec_env(ENV_ID, n_envs=1, seed=0)
    sac = SAC("MlpPolicy", env, seed=0, learning_starts=200, batch_size=64)
    sac.learn(200)
    sera = serasac_as_sac(env)
    sera.learn(1)  # sets up the logger
    sera.policy.load_state_dict(sac.policy.state_dict())
    sera.replay_buffer = copy.deepcopy(sac.replay_buffer)
    for step in range(3):
        losses = {}
        for model in (sac, sera):
            np.random.seed(step)
            th.manual_seed(step)
            model.train(gradient_steps=1, batch_size=64)
            losses[type(model).__name__] = {
                key: model.logger.name_to_value[f"train/{key}"] for key in ("critic_loss", "actor_loss", "ent_coef_loss")
            }
        for key, value in losses["SAC"].items():
            assert losses["SERASAC"][key] == pytest.approx(value, rel=1e-4, abs=1e-6), (step, key)
        for (name, p_sac), p_sera in zip(sac.policy.state_dict().items(), sera.policy.state_dict().values(), strict=True):
            assert th.allclose(p_sac, p_sera, atol=1e-5), (step, name)


def test_non_finite_target_stops_before_any_change():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(100)
    before = snapshot(model)
    model.replay_buffer.rewards[:] = np.nan
    with pytest.raises(FloatingPointError, match=r"Non-finite TD target at gradient step \d+"):
        model.train(gradient_steps=1, batch_size=32)
    assert_same_state(before, snapshot(model))


def test_non_finite_entropy_coefficient_is_named():
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(100)
    with th.no_grad():
        model.log_ent_coef.fill_(float("inf"))  # type: ignore[union-attr]
    with pytest.raises(FloatingPointError, match="entropy coefficient"):
        model.train(gradient_steps=1, batch_size=32)


def test_save_load_continue(tmp_path):
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(200)
    observations = np.stack([model.observation_space.sample() for _ in range(8)])
    actions, _ = model.predict(observations, deterministic=True)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")

    loaded = SERASAC.load(tmp_path / "model", env=make_vec_env(ENV_ID, n_envs=1))
    loaded_actions, _ = loaded.predict(observations, deterministic=True)
    np.testing.assert_array_equal(actions, loaded_actions)
    assert_same_state(snapshot(model), snapshot(loaded))
    assert loaded.step_size.initialized
    assert [g["lr"] for g in loaded.critic.optimizer.param_groups] == [g["lr"] for g in model.critic.optimizer.param_groups]
    assert loaded.policy.critic_archs == model.policy.critic_archs
    assert loaded.sera_alpha == model.sera_alpha and loaded.target_aggregation == "sera"

    loaded.load_replay_buffer(tmp_path / "buffer")
    assert loaded.replay_buffer is not None and loaded.replay_buffer.size() == model.replay_buffer.size()
    state_before = loaded.step_size.td_error_var.clone()
    loaded.learn(60, reset_num_timesteps=False)
    assert loaded.num_timesteps == 260
    assert loaded._n_updates > model._n_updates
    assert not th.equal(loaded.step_size.td_error_var, state_before)


def test_policy_saves_and_loads_on_its_own(tmp_path):
    model = SERASAC("MlpPolicy", ENV_ID, seed=0, policy_kwargs=dict(n_critics=3, critic_archs=[[8], [16], [8, 8]]), **SMALL)
    model.policy.save(tmp_path / "policy.pth")
    policy = type(model.policy).load(tmp_path / "policy.pth")
    assert policy.critic_archs == [[8], [16], [8, 8]]
    observation = model.observation_space.sample()
    np.testing.assert_array_equal(
        policy.predict(observation, deterministic=True)[0], model.predict(observation, deterministic=True)[0]
    )


def test_deterministic_training():
    def run() -> dict[str, th.Tensor]:
        return snapshot(SERASAC("MlpPolicy", ENV_ID, seed=3, **SMALL).learn(150))

    assert_same_state(run(), run())


def test_multi_env_progress_bar_and_evaluation():
    env = make_vec_env(ENV_ID, n_envs=2, seed=0)
    model = SERASAC("MlpPolicy", env, seed=0, **SMALL).learn(200, progress_bar=True)
    assert model.num_timesteps == 200
    mean_return, _ = evaluate_policy(model, env, n_eval_episodes=2)
    assert np.isfinite(mean_return)


class DictObservation(gym.ObservationWrapper):
    """Pendulum with its observation split into a Dict."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        box = env.observation_space
        assert isinstance(box, spaces.Box)
        self.observation_space = spaces.Dict(
            {"angle": spaces.Box(box.low[:2], box.high[:2]), "velocity": spaces.Box(box.low[2:], box.high[2:])}
        )

    def observation(self, observation):
        return {"angle": observation[:2], "velocity": observation[2:]}


def test_multi_input_policy(tmp_path):
    env = DictObservation(gym.make(ENV_ID))
    model = SERASAC("MultiInputPolicy", env, seed=0, **SMALL).learn(120)
    observation = env.observation_space.sample()
    model.save(tmp_path / "model")
    loaded = SERASAC.load(tmp_path / "model")
    np.testing.assert_array_equal(
        model.predict(observation, deterministic=True)[0], loaded.predict(observation, deterministic=True)[0]
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(sera_alpha=1.5), r"sera_alpha=1\.5 is out of range: allowed \[0\.0, 1\.0\]"),
        (dict(sera_temperature=0.0), r"sera_temperature=0\.0 is out of range: allowed \(0\.0, inf\)"),
        (
            dict(sera_temperature_mode="log"),
            "sera_temperature_mode='log' is invalid: expected one of 'absolute', 'relative'",
        ),
        (
            dict(target_aggregation="max"),
            "target_aggregation='max' is invalid: expected one of 'sera', 'mean', 'median', 'min'",
        ),
        (dict(actor_aggregation="sera"), "actor_aggregation='sera' is invalid"),
        (dict(critic_lr_max=-1e-4), "critic_lr_max"),
        (dict(kappa_min=1.2), "kappa_min"),
        (dict(kappa_eps=0), "kappa_eps"),
        (dict(td_variance_ema=1.0), r"td_variance_ema=1\.0 is out of range: allowed \[0\.0, 1\.0\)"),
        (dict(estimation_variance_ema=-0.1), "estimation_variance_ema"),
        (dict(disagreement_coef=-0.01), "disagreement_coef"),
        (dict(critic_learning_rate=0.0), "critic_learning_rate"),
        (dict(sera_include_median="yes"), "sera_include_median"),
        (dict(learning_rate=float("nan")), "learning_rate=nan is invalid"),
        (dict(gamma=1.1), "gamma"),
        (dict(tau=-0.5), "tau"),
        (dict(batch_size=0), "batch_size=0 is out of range: allowed an integer >= 1"),
        (dict(buffer_size=0), "buffer_size"),
        (dict(target_update_interval=0), "target_update_interval"),
        (dict(ent_coef="automatic"), "ent_coef='automatic' is invalid"),
        (dict(ent_coef=-1.0), "ent_coef"),
        (dict(policy_kwargs=dict(n_critics=1)), "n_critics=1 is out of range"),
        (dict(policy_kwargs=dict(n_critics=3, critic_archs=[[8], [8]])), "critic_archs has 2 entries but n_critics=3"),
        (dict(policy_kwargs=dict(n_critics=2, critic_archs=[[8], [0]])), r"critic_archs\[1\]"),
    ],
)
def test_invalid_hyperparameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SERASAC("MlpPolicy", ENV_ID, **kwargs)


def test_discrete_actions_are_not_supported():
    with pytest.raises(AssertionError, match="only supports"):
        SERASAC("MlpPolicy", "CartPole-v1")


def test_trains_with_hindsight_experience_replay_on_a_goal_env_and_goes_on_after_loading(tmp_path):
    # SB3's HER with SERASAC's MultiInputPolicy, as SB3's own HER tests run it: continuous bit flipping
    from stable_baselines3 import HerReplayBuffer
    from stable_baselines3.common.envs import BitFlippingEnv

    env = BitFlippingEnv(n_bits=4, continuous=True)
    her = dict(
        replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(n_sampled_goal=2, goal_selection_strategy="future")
    )
    model = SERASAC("MultiInputPolicy", env, learning_starts=100, batch_size=16, buffer_size=500, seed=0, **her)
    model.learn(150)
    assert model._n_updates > 0 and isinstance(model.replay_buffer, HerReplayBuffer)
    model.save(tmp_path / "her")
    loaded = SERASAC.load(tmp_path / "her", env=env)
    assert isinstance(loaded.replay_buffer, HerReplayBuffer)
    loaded.learn(30, reset_num_timesteps=False)
    assert loaded.num_timesteps == 180


def test_a_file_of_another_algorithm_or_ensemble_is_named_in_one_line(tmp_path):
    SAC("MlpPolicy", ENV_ID, buffer_size=100).save(tmp_path / "sac")
    # SB3's own error was KeyError: 'policy.optimizer'
    with pytest.raises(ValueError, match=r"holds a model of another algorithm: its policy is stable_baselines3\.sac"):
        SERASAC.load(tmp_path / "sac")
    SERASAC("MlpPolicy", ENV_ID, policy_kwargs=dict(n_critics=3), buffer_size=100).save(tmp_path / "three")
    # torch's own listed every missing weight of critics 3 and 4
    with pytest.raises(ValueError, match=r"built with policy_kwargs=\{'n_critics': 3\}, where this model has policy_kwargs"):
        SERASAC("MlpPolicy", ENV_ID, buffer_size=100).set_parameters(str(tmp_path / "three.zip"))
    assert SERASAC.load(tmp_path / "three").critic.n_critics == 3
