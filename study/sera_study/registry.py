"""
Names the run engine resolves: rl-zoo3's algorithms with this package's, Gymnasium's task ids, and a task's default
hyperparameters as ``sb3-sera train`` takes them: the task's entry in ``hyperparams/<algo>.yml`` (this package's
file, else rl-zoo3's own), with the keys each algorithm accepts.
"""

import difflib
import inspect
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_sera.zoo import ALGOS as ZOO_ALGOS
from sb3_sera.zoo import HYPERPARAMS_DIR

#: rl-zoo3 keys that describe the run rather than the algorithm
RUN_KEYS = ("n_timesteps", "policy", "n_envs", "env_kwargs", "noise_type", "noise_std")
#: rl-zoo3 keys this engine does not apply: such entries are for ``sb3-sera train``
ZOO_ONLY_KEYS = ("normalize", "normalize_kwargs", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback")
#: Keys a run's settings never take (the engine sets them)
ENGINE_KEYS = ("policy", "env", "seed", "verbose", "device", "tensorboard_log", "_init_setup_model")
#: The settings two arms of a comparison share unless it studies them (beside the budget and the evaluations, which
#: a grid or a ``compare`` command sets for every arm at once)
SHARED_SETTINGS = ("learning_starts", "batch_size", "buffer_size", "gamma", "tau", "train_freq", "gradient_steps")


def algorithm_classes() -> dict[str, type[BaseAlgorithm]]:
    """rl-zoo3's algorithms by lower-case name, with this package's added."""
    with warnings.catch_warnings():
        # rl-zoo3 imports huggingface_hub, whose tqdm.auto warns in a notebook without ipywidgets: no bar is drawn here
        warnings.filterwarnings("ignore", message="IProgress not found")
        from rl_zoo3.utils import ALGOS

    return {**ALGOS, **ZOO_ALGOS}


def _entries(path: Path) -> dict[str, Any]:
    return (yaml.safe_load(path.read_text()) or {}) if path.exists() else {}


def hyperparams_file(algo: str, env_id: str | None = None) -> Path:
    """
    The YAML file ``sb3-sera train --algo <algo> --env <env_id>`` reads: this package's where it has an entry for the
    task (or no task is named), else rl-zoo3's own. The package's ``sac.yml`` names only the paper's tasks, so stock
    SAC on any other task keeps rl-zoo3's entries.
    """
    ours = Path(HYPERPARAMS_DIR) / f"{algo}.yml"
    import rl_zoo3

    zoo = Path(rl_zoo3.__file__).parent / "hyperparams" / f"{algo}.yml"
    if not ours.exists():
        return zoo
    if env_id is None or not zoo.exists() or env_id in _entries(ours):
        return ours
    return zoo


def default_hyperparams(algo: str, env_id: str) -> tuple[dict[str, Any], str]:
    """
    The task's entry in ``hyperparams_file(algo)`` (its ``default`` entry when the task has none), as rl-zoo3 reads it.

    :return: the entry, and where it came from (``"<file>:<key>"``, or a sentence saying the algorithm's own
        defaults apply because no file has an entry)
    """
    path = hyperparams_file(algo, env_id)
    entries = _entries(path)
    # Named as the repository holds it (hyperparams/serasac.yml; rl-zoo3's: rl_zoo3/hyperparams/sac.yml), never by
    # the absolute path of this machine
    where = f"hyperparams/{path.name}" if path.parent == HYPERPARAMS_DIR else f"rl_zoo3/hyperparams/{path.name}"
    for key in (env_id, "default"):
        if key in entries:
            return dict(entries[key]), f"{where}:{key}"
    return {}, f"no entry for {env_id} in {where}: the algorithm's defaults"


def accepted_hyperparams(algo: str) -> set[str]:
    """What a run of ``algo`` may set: the algorithm's constructor arguments and rl-zoo3's run keys."""
    signature = inspect.signature(algorithm_classes()[algo])
    return (set(signature.parameters) - set(ENGINE_KEYS)) | (set(RUN_KEYS) - {"n_timesteps"})


def algorithm_default(algo: str, key: str) -> Any:
    """The default of ``key`` in the constructor of ``algo`` (rl-zoo3's name), or "unknown"."""
    model_class = algorithm_classes().get(algo)
    if model_class is None:
        return "unknown"
    parameter = inspect.signature(model_class).parameters.get(key)
    return "unknown" if parameter is None or parameter.default is inspect.Parameter.empty else parameter.default


def shared_settings(algo: str, hyperparams: dict[str, Any]) -> dict[str, Any]:
    """
    The :data:`SHARED_SETTINGS` a run of ``algo`` trains with: its hyperparameters', else the algorithm's defaults.
    An on-policy algorithm shares ``gamma`` alone (its ``batch_size`` is a minibatch of a rollout, not a replay
    sample), and a setting the algorithm does not take is left out.
    """
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    takes = accepted_hyperparams(algo)
    if not issubclass(algorithm_classes()[algo], OffPolicyAlgorithm):
        takes &= {"gamma"}
    return {
        key: plain_value(hyperparams[key]) if key in hyperparams else algorithm_default(algo, key)
        for key in SHARED_SETTINGS
        if key in takes
    }


def plain_value(value: Any) -> Any:
    """A setting as compared: a whole float as an int (``1e4`` equals ``10000``), a tuple as a list."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, tuple | list):
        return [plain_value(item) for item in value]
    return value


def unmatched_settings(settings: dict[str, dict[str, Any]], studied: Sequence[str] = ()) -> dict[str, dict[str, Any]]:
    """
    The shared settings whose values differ between arms, leaving out those ``studied``.

    :param settings: per arm (a variant's name), its :func:`shared_settings` (with the budget and evaluation settings
        where the caller compares those too)
    :return: per differing setting, each arm's value (an arm that does not take the setting is left out)
    """
    keys = sorted({key for values in settings.values() for key in values} - set(studied))
    differing = {}
    for key in keys:
        values = {arm: values[key] for arm, values in settings.items() if key in values}
        if len({repr(value) for value in values.values()}) > 1:
            differing[key] = values
    return differing


def unmatched_text(differing: dict[str, dict[str, Any]]) -> str:
    """``key: arm=value, arm=value; ...`` for :func:`unmatched_settings`."""
    return "; ".join(
        f"{key}: {', '.join(f'{arm}={value}' for arm, value in values.items())}" for key, values in differing.items()
    )


def check_hyperparams(algo: str, hyperparams: dict[str, Any], where: str) -> None:
    """Raise ``ValueError`` naming the keys ``algo`` does not take (``where`` says whose settings they are)."""
    zoo_only = sorted(set(hyperparams) & set(ZOO_ONLY_KEYS))
    if zoo_only:
        raise ValueError(
            f"{where}: {zoo_only} are applied by rl-zoo3's training only: run this task with `sb3-sera train`, "
            "or give an entry without them"
        )
    check_known(algo, hyperparams, accepted_hyperparams(algo), where)


def check_known(algo: str, hyperparams: dict[str, Any], allowed: set[str], where: str) -> None:
    """Raise ``ValueError`` naming the keys of ``hyperparams`` not in ``allowed``, with the nearest allowed names."""

    unknown = sorted(set(hyperparams) - allowed)
    if unknown:
        hints = "; ".join(_unknown_key_hint(algo, key, allowed) for key in unknown if _unknown_key_hint(algo, key, allowed))
        raise ValueError(
            f"{where}: unknown hyperparameter(s) {unknown} for {algo}{'; ' + hints if hints else ''}; "
            f"allowed: {sorted(allowed)}"
        )


def _unknown_key_hint(algo: str, key: str, allowed: set[str]) -> str:
    """
    What to say of ``key``, which ``algo`` does not take: that an on-policy algorithm takes no off-policy setting
    (SAC's ``learning_starts`` for PPO), else its nearest allowed name; empty where there is none.
    """
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    model_class = algorithm_classes().get(algo)
    off_policy_only = set(inspect.signature(SAC).parameters) - set(inspect.signature(PPO).parameters)
    if model_class is not None and issubclass(model_class, OnPolicyAlgorithm) and key in off_policy_only:
        return (
            f"{algo} is on-policy and takes no {key!r} (an off-policy algorithm's setting): give it to the off-policy "
            f"algorithms alone (-params <algo>:{key}:<value>)"
        )
    match = difflib.get_close_matches(key, allowed, n=1)
    return f"did you mean {match[0]!r} for {key!r}?" if match else ""


def check_task(env_id: str) -> None:
    """Raise ``ValueError`` for an env id Gymnasium does not know, listing this package's ids."""
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=3)
        hint = f"did you mean {' or '.join(repr(name) for name in close)}? " if close else ""
        registered = sorted(name for name in gym.registry if name.startswith("sb3_sera/"))
        raise ValueError(f"unknown task {env_id!r}; {hint}registered ids include {registered} and Gymnasium's")
