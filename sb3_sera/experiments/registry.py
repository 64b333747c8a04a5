"""
Names the run engine resolves: rl-zoo3's algorithms with this package's, Gymnasium's task ids, and a task's default
hyperparameters as ``sb3-sera train`` takes them: the task's entry in ``hyperparams/<algo>.yml`` (this package's
file, else rl-zoo3's own), with the keys each algorithm accepts.
"""

import inspect
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml
from stable_baselines3.common.base_class import BaseAlgorithm

#: rl-zoo3 keys that describe the run rather than the algorithm
RUN_KEYS = ("n_timesteps", "policy", "n_envs", "env_kwargs", "noise_type", "noise_std")
#: rl-zoo3 keys this engine does not apply: such entries are for ``sb3-sera train``
ZOO_ONLY_KEYS = ("normalize", "normalize_kwargs", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback")
#: Keys a run's settings never take (the engine sets them)
ENGINE_KEYS = ("policy", "env", "seed", "verbose", "device", "tensorboard_log", "_init_setup_model")


def algorithm_classes() -> dict[str, type[BaseAlgorithm]]:
    """rl-zoo3's algorithms by lower-case name, with this package's added."""
    from rl_zoo3.utils import ALGOS

    from sb3_sera.experiments.zoo import ZOO_ALGOS

    return {**ALGOS, **ZOO_ALGOS}


def _entries(path: Path) -> dict[str, Any]:
    return (yaml.safe_load(path.read_text()) or {}) if path.exists() else {}


def hyperparams_file(algo: str, env_id: str | None = None) -> Path:
    """
    The YAML file ``sb3-sera train --algo <algo> --env <env_id>`` reads: this package's where it has an entry for the
    task (or no task is named), else rl-zoo3's own. The package's ``sac.yml`` names only the paper's tasks, so stock
    SAC on any other task keeps rl-zoo3's entries.
    """
    from sb3_sera.experiments.zoo import HYPERPARAMS_DIR

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
    from sb3_sera.experiments.zoo import HYPERPARAMS_DIR

    where = f"hyperparams/{path.name}" if path.parent == HYPERPARAMS_DIR else f"rl_zoo3/hyperparams/{path.name}"
    for key in (env_id, "default"):
        if key in entries:
            return dict(entries[key]), f"{where}:{key}"
    return {}, f"no entry for {env_id} in {where}: the algorithm's defaults"


def accepted_hyperparams(algo: str) -> set[str]:
    """What a run of ``algo`` may set: the algorithm's constructor arguments and rl-zoo3's run keys."""
    signature = inspect.signature(algorithm_classes()[algo])
    return (set(signature.parameters) - set(ENGINE_KEYS)) | (set(RUN_KEYS) - {"n_timesteps"})


def check_hyperparams(algo: str, hyperparams: dict[str, Any], where: str) -> None:
    """Raise ``ValueError`` naming the keys ``algo`` does not take (``where`` says whose settings they are)."""
    zoo_only = sorted(set(hyperparams) & set(ZOO_ONLY_KEYS))
    if zoo_only:
        raise ValueError(
            f"{where}: {zoo_only} are applied by rl-zoo3's training only: run this task with `sb3-sera train`, "
            "or give an entry without them"
        )
    unknown = sorted(set(hyperparams) - accepted_hyperparams(algo))
    if unknown:
        raise ValueError(
            f"{where}: unknown hyperparameter(s) {unknown} for {algo}; allowed: {sorted(accepted_hyperparams(algo))}"
        )


def check_task(env_id: str) -> None:
    """Raise ``ValueError`` for an env id Gymnasium does not know, listing this package's ids."""
    if env_id not in gym.registry:
        registered = sorted(name for name in gym.registry if name.startswith("sb3_sera/"))
        raise ValueError(f"unknown task {env_id!r}; registered ids include {registered} and Gymnasium's")
