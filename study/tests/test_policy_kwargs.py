"""policy_kwargs given as text are parsed, never executed."""

import pytest
import torch as th
from torch import nn

from sera_study.runs import engine, specs
from sera_study.runs.policy_kwargs import parse_policy_kwargs


def test_literals_dicts_and_known_names():
    assert parse_policy_kwargs("dict(net_arch=[256, 256], activation_fn=nn.ReLU, log_std_init=-3)") == {
        "net_arch": [256, 256],
        "activation_fn": nn.ReLU,
        "log_std_init": -3,
    }
    assert parse_policy_kwargs("{'net_arch': {'pi': [64], 'qf': (400, 300)}, 'optimizer_class': th.optim.AdamW}") == {
        "net_arch": {"pi": [64], "qf": (400, 300)},
        "optimizer_class": th.optim.AdamW,
    }
    assert parse_policy_kwargs("dict(share_features_extractor=False, n_critics=None)") == {
        "share_features_extractor": False,
        "n_critics": None,
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("__import__('os').system('touch {marker}')", r"is not allowed; write literals"),
        ("dict(a=open('{marker}', 'w'))", r"open\(.*is not allowed"),
        ("dict(**{{'a': 1}})", r"'\*\*' unpacking is not allowed"),
        ("nn.Module.__subclasses__()", r"is not allowed"),
        ("[1, 2]", r"must be a dict, got list"),
        ("dict(a=", r"is not a Python expression"),
    ],
)
def test_code_is_refused_and_never_runs(tmp_path, text, message):
    marker = tmp_path / "marker"
    with pytest.raises(ValueError, match=message):
        parse_policy_kwargs(text.format(marker=marker))
    assert not marker.exists()


def test_params_on_the_command_line_never_execute_code(tmp_path):
    marker = tmp_path / "marker"
    spec = specs.make_spec(
        variant="serasac",
        algo="serasac",
        env_id="Pendulum-v1",
        seed=0,
        n_timesteps=200,
        overrides={"policy_kwargs": f"__import__('os').system('touch {marker}')"},
        eval_freq=100,
    )
    with pytest.raises(ValueError, match="is not allowed"):
        engine.check_specs([spec])
    assert not marker.exists()


def test_a_shared_policy_kwargs_dict_is_not_changed_by_sb3():
    shared = {"net_arch": [32, 32]}
    spec = specs.make_spec(
        variant="sac",
        algo="sac",
        env_id="Pendulum-v1",
        seed=0,
        n_timesteps=200,
        overrides={"policy_kwargs": shared, "use_sde": True},
        eval_freq=100,
    )
    engine.check_specs([spec])
    assert shared == {"net_arch": [32, 32]}
