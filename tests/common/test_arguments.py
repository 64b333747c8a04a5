"""What a new user's first mistakes get: errors that name what is wrong and what is allowed."""

import inspect
import re

import gymnasium as gym
import numpy as np
import pytest
from mpe2 import simple_spread_v3
from stable_baselines3 import SAC

from sb3_sera import ACE, IET, MADDPG, MAPPO, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.ctde import mamujoco_parallel_env
from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.ctde.execution import DecentralizedActors

#: Each algorithm, the policy and env it is built with, and a misspelled keyword with the one it misspells
TYPOS = {
    SERASAC: ("MlpPolicy", "Pendulum-v1", "sera_alpah", "sera_alpha"),
    SUNRISE: ("MlpPolicy", "Pendulum-v1", "n_member", "n_members"),
    ACE: ("MlpPolicy", "Pendulum-v1", "exploration_nosie", "exploration_noise"),
    IET: ("CTDEPolicy", "sb3_sera/SimpleSpread-v0", "latent_dm", "latent_dim"),
    MASAC: ("CTDEPolicy", "sb3_sera/SimpleSpread-v0", "learnig_rate", "learning_rate"),
    MATD3: ("CTDEPolicy", "sb3_sera/SimpleSpread-v0", "policy_dealy", "policy_delay"),
    MADDPG: ("CTDEPolicy", "sb3_sera/SimpleSpread-v0", "bufer_size", "buffer_size"),
    MAPPO: ("CTDEPolicy", "sb3_sera/SimpleSpread-v0", "n_step", "n_steps"),
}
#: A multi-agent algorithm of each family, and the single-agent ones, for the PettingZoo env checks
ALGORITHMS = {
    SERASAC: "CTDEPolicy",
    MASAC: "CTDEPolicy",
    MAPPO: "CTDEPolicy",
    IET: "CTDEPolicy",
    SUNRISE: "MlpPolicy",
    ACE: "MlpPolicy",
}


def listed_keywords(message: str) -> list[str]:
    """The keyword names listed at the end of an unknown keyword's message."""
    match = re.search(r"keyword arguments are: (.*)$", message)
    assert match is not None, message
    return match.group(1).split(", ")


@pytest.mark.parametrize("algo", TYPOS, ids=lambda algo: algo.__name__)
def test_a_typo_names_the_keyword_its_close_matches_and_every_keyword(algo):
    policy, env, typo, meant = TYPOS[algo]
    with pytest.raises(TypeError) as error:
        algo(policy, env, **{typo: 1})
    message = str(error.value)
    assert message.startswith(f"{algo.__name__} got an unexpected keyword argument {typo!r}"), message
    # Close matches first, then every keyword of the algorithm (the public ones)
    assert message.index(f"Did you mean {meant!r}") < message.index("keyword arguments are:")
    public = [name for name in inspect.signature(algo).parameters if not name.startswith("_")]
    assert listed_keywords(message) == public


def test_an_iet_typo_names_iet_and_its_latent_dim():
    with pytest.raises(TypeError) as error:
        IET("CTDEPolicy", "sb3_sera/SimpleSpread-v0", learning_rat=1e-3)
    message = str(error.value)
    assert "IET got" in message and "SAC" not in message
    assert "'learning_rate'" in message and "latent_dim" in listed_keywords(message)


def test_several_unknown_keywords_are_all_named():
    with pytest.raises(TypeError, match=r"unexpected keyword arguments 'sera_alpah' and 'kapa_min'.*'kappa_min'"):
        SERASAC("MlpPolicy", "Pendulum-v1", sera_alpah=0.3, kapa_min=0.1)


@pytest.mark.parametrize(
    ("algo", "policy", "env", "keyword"),
    [
        (ACE, "MlpPolicy", "Pendulum-v1", "n_actors"),
        (ACE, "MlpPolicy", "Pendulum-v1", "depth"),
        (ACE, "MlpPolicy", "Pendulum-v1", "normalize_observations"),
        (SERASAC, "MlpPolicy", "Pendulum-v1", "n_critics"),
        (SERASAC, "MlpPolicy", "Pendulum-v1", "critic_archs"),
        (SERASAC, "CTDEPolicy", "sb3_sera/SimpleSpread-v0", "share_actor"),
        (MASAC, "CTDEPolicy", "sb3_sera/SimpleSpread-v0", "net_arch"),
        (SUNRISE, "MlpPolicy", "Pendulum-v1", "net_arch"),
    ],
)
def test_a_policy_argument_given_to_the_algorithm_says_policy_kwargs(algo, policy, env, keyword):
    with pytest.raises(TypeError) as error:
        algo(policy, env, **{keyword: 3})
    message = str(error.value)
    assert f"{keyword!r} is an argument of the policy" in message
    assert f"policy_kwargs=dict({keyword}=3)" in message
    assert "policy_kwargs" in listed_keywords(message)


def test_policy_arguments_are_those_of_the_policy_given():
    # share_actor belongs to the CTDE policies: with "MlpPolicy" it is no policy argument either
    with pytest.raises(TypeError) as error:
        SERASAC("MlpPolicy", "Pendulum-v1", share_actor=True)
    assert "policy_kwargs=dict(" not in str(error.value)


def test_signatures_are_unchanged():
    # MASAC: SAC's, and compile_update
    masac = inspect.signature(MASAC).parameters
    assert [name for name in masac if name != "compile_update"] == list(inspect.signature(SAC).parameters)
    assert masac["compile_update"].default is False
    for algo, first in ((SERASAC, "sera_alpha"), (SUNRISE, "n_members"), (ACE, "exploration_noise")):
        parameters = inspect.signature(algo).parameters
        assert list(parameters)[:2] == ["policy", "env"] and first in parameters
        assert not any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values())
    assert list(inspect.signature(IET).parameters)[-1] == "latent_dim"


def test_errors_raised_inside_the_constructor_are_unchanged():
    # A wrong value of a known keyword keeps its own error
    with pytest.raises(ValueError, match=r"sera_alpha=2 is out of range"):
        SERASAC("MlpPolicy", "Pendulum-v1", sera_alpha=2)
    with pytest.raises(TypeError, match=r"positional argument"):
        SUNRISE("MlpPolicy")


@pytest.mark.parametrize("algo", ALGORITHMS, ids=lambda algo: algo.__name__)
def test_a_pettingzoo_parallel_env_says_to_wrap_it_in_ctde_env(algo):
    with pytest.raises(TypeError) as error:
        algo(ALGORITHMS[algo], simple_spread_v3.parallel_env(continuous_actions=True))
    message = str(error.value)
    assert f"{algo.__name__} got the PettingZoo ParallelEnv" in message
    assert "sb3_sera.CTDEEnv(parallel_env)" in message and "'CTDEPolicy'" in message


def test_a_pettingzoo_aec_env_says_to_convert_it_first():
    with pytest.raises(TypeError) as error:
        MASAC("CTDEPolicy", simple_spread_v3.env(continuous_actions=True))
    message = str(error.value)
    assert "AEC env" in message
    assert "pettingzoo.utils.aec_to_parallel(env)" in message and "sb3_sera.CTDEEnv(parallel_env)" in message


def test_a_mamujoco_parallel_env_says_to_wrap_it_in_ctde_env():
    with pytest.raises(TypeError, match=r"SERASAC got the PettingZoo ParallelEnv .*sb3_sera\.CTDEEnv\(parallel_env\)"):
        SERASAC("CTDEPolicy", mamujoco_parallel_env("HalfCheetah", "2x3"))


@pytest.fixture(scope="module")
def controllers() -> DecentralizedActors:
    model = MASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=10, buffer_size=100)
    return DecentralizedActors.from_model(model)


def test_controllers_take_a_ctde_env_observation(controllers):
    env = gym.make("sb3_sera/SimpleSpread-v0")
    observation, _ = env.reset(seed=0)
    assert STATE_KEY in observation
    actions = controllers(observation)
    local = {agent: value for agent, value in observation.items() if agent != STATE_KEY}
    assert list(actions) == list(local)
    for agent, action in controllers(local).items():
        np.testing.assert_array_equal(actions[agent], action)


def test_controllers_name_the_agents_they_expect(controllers):
    with pytest.raises(ValueError) as error:
        controllers({"agent_0": np.zeros(18, dtype=np.float32), "walker_7": np.zeros(18, dtype=np.float32)})
    message = str(error.value)
    assert "'walker_7'" in message and "'agent_0', 'agent_1', 'agent_2'" in message and "keyed by agent name" in message
    with pytest.raises(ValueError, match=r"expected a dict of per-agent observations.*got ndarray"):
        controllers(np.zeros(18, dtype=np.float32))


@pytest.mark.parametrize(
    ("algo", "policy", "env", "typo", "meant"),
    [
        (SERASAC, "MlpPolicy", "Pendulum-v1", "n_critic", "n_critics"),
        (MASAC, "CTDEPolicy", "sb3_sera/SimpleSpread-v0", "share_actors", "share_actor"),
    ],
)
def test_a_typo_in_policy_kwargs_names_it_and_its_close_matches(algo, policy, env, typo, meant):
    with pytest.raises(TypeError, match=rf"got '{typo}' in policy_kwargs\. Did you mean '{meant}'") as error:
        algo(policy, env, policy_kwargs={typo: 3})
    assert meant in listed_keywords(str(error.value))


@pytest.mark.parametrize(
    ("critic_archs", "message"),
    [
        ("big", r"critic_archs='big' is invalid: give a list of n_critics=5 lists of hidden layer sizes"),
        (["64", "64"], r"critic_archs\[0\]='64' is invalid: each critic's entry is a list of hidden layer sizes"),
        ([[64]] * 4, r"critic_archs has 4 entries but n_critics=5"),
    ],
)
def test_critic_archs_that_are_not_lists_of_sizes_are_named(critic_archs, message):
    with pytest.raises(ValueError, match=message):
        SERASAC("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(critic_archs=critic_archs))


def test_one_actor_for_agents_of_different_action_sizes_is_advised_against_sharing():
    # MaMuJoCo's Humanoid 9|8: the observations padded alike, the agents acting 9 and 8 joints, which no padding helps
    humanoid = gym.make("sb3_sera/MaMuJoCo-v0", scenario="Humanoid", agent_conf="9|8", agent_indicator=True)
    with pytest.raises(ValueError, match=r"one actor cannot act for agents whose action sizes differ") as error:
        MASAC("CTDEPolicy", humanoid, buffer_size=100, policy_kwargs=dict(share_actor=True))
    assert "agent_indicator" not in str(error.value)
