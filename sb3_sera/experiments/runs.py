"""
The run engine behind ``compare``, ``bench`` and the notebooks: one way to describe a training run, to resolve its
hyperparameters and to record it, in rl-zoo3's layout so that the zoo's own runs read the same way.

Hyperparameters come from where ``sb3-sera train`` takes them: the task's entry in ``hyperparams/<algo>.yml`` (this
package's file, else rl-zoo3's own), then the variant's or the command line's overrides. A run lives in
``<out>/<variant>/<env_name>_<id>/`` (ids from 1, as the zoo numbers them) and holds, as the zoo writes them,
``<env_name>/config.yml`` (the resolved hyperparameters) and ``<env_name>/args.yml`` (algorithm, variant, env id,
seed, budget, evaluation settings, threads, device, where the hyperparameters came from, the package versions, and
the git commit of the code that ran with whether its tree was clean),
then ``evaluations.npz`` and the callback's records, ``0.monitor.csv``, TensorBoard events under
``<variant>_seed<seed>_1/``, the final model ``<env_name>.zip`` and, written last, ``result.json`` (wall time, and
the torch threads and device the run had). A run whose
records match a finished run's is not run again; an interrupted one runs again in its own folder.
"""

import contextlib
import copy
import json
import math
import os
import platform
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import VecEnv
from tqdm import tqdm

from sb3_sera.common.mujoco_log import route_mujoco_warnings
from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.experiments.evaluation import BIAS_FILE, InitialStateBiasCallback, initial_state_bias
from sb3_sera.experiments.policy_kwargs import parse_policy_kwargs

#: rl-zoo3 keys that describe the run rather than the algorithm
RUN_KEYS = ("n_timesteps", "policy", "n_envs", "env_kwargs", "noise_type", "noise_std")
#: rl-zoo3 keys this engine does not apply: such entries are for ``sb3-sera train``
ZOO_ONLY_KEYS = ("normalize", "normalize_kwargs", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback")
#: Keys a run's settings never take (the engine sets them)
ENGINE_KEYS = ("policy", "env", "seed", "verbose", "device", "tensorboard_log", "_init_setup_model")
#: Packages whose versions each run records
VERSIONED = ("sb3-sera", "stable-baselines3", "sb3-contrib", "rl-zoo3", "torch", "gymnasium", "gymnasium-robotics")
#: File that marks a run as finished (written last)
RESULT_FILE = "result.json"
#: What reading a damaged ``.npz`` record raises
NPZ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def algorithm_classes() -> dict[str, type[BaseAlgorithm]]:
    """rl-zoo3's algorithms by lower-case name, with this package's added."""
    from rl_zoo3.utils import ALGOS

    from sb3_sera.experiments.zoo import ZOO_ALGOS

    return {**ALGOS, **ZOO_ALGOS}


def env_name(env_id: str) -> str:
    """``env_id`` as rl-zoo3 names folders and files: slashes become dashes (``sb3_sera-HalfCheetah-6x1-v0``)."""
    return env_id.replace("/", "-")


def hyperparams_file(algo: str) -> Path:
    """The YAML file ``sb3-sera train --algo <algo>`` reads: this package's, else rl-zoo3's own."""
    from sb3_sera.experiments.zoo import HYPERPARAMS_DIR

    ours = Path(HYPERPARAMS_DIR) / f"{algo}.yml"
    if ours.exists():
        return ours
    import rl_zoo3

    return Path(rl_zoo3.__file__).parent / "hyperparams" / f"{algo}.yml"


def default_hyperparams(algo: str, env_id: str) -> tuple[dict[str, Any], str]:
    """
    The task's entry in ``hyperparams_file(algo)`` (its ``default`` entry when the task has none), as rl-zoo3 reads it.

    :return: the entry, and where it came from (``"<file>:<key>"``, or a sentence saying the algorithm's own
        defaults apply because no file has an entry)
    """
    path = hyperparams_file(algo)
    entries = yaml.safe_load(path.read_text()) if path.exists() else {}
    # Named as the repository holds it (hyperparams/serasac.yml; rl-zoo3's: rl_zoo3/hyperparams/sac.yml), never by
    # the absolute path of this machine
    from sb3_sera.experiments.zoo import HYPERPARAMS_DIR

    where = f"hyperparams/{path.name}" if path.parent == HYPERPARAMS_DIR else f"rl_zoo3/hyperparams/{path.name}"
    for key in (env_id, "default"):
        if key in (entries or {}):
            return dict(entries[key]), f"{where}:{key}"
    return {}, f"no entry for {env_id} in {where}: the algorithm's defaults"


def accepted_hyperparams(algo: str) -> set[str]:
    """What a run of ``algo`` may set: the algorithm's constructor arguments and rl-zoo3's run keys."""
    import inspect

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


@dataclass
class RunSpec:
    """One training run: an algorithm under a variant's name, on one task and seed, with resolved hyperparameters."""

    variant: str
    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    #: Resolved hyperparameters as written in a zoo YAML entry (``policy`` included, ``n_timesteps`` left out)
    hyperparams: dict[str, Any] = field(default_factory=dict)
    eval_freq: int = 1000
    n_eval_episodes: int = 5
    #: torch threads of the run's process (None: torch's default)
    num_threads: int | None = 1
    device: str = "auto"
    #: Where the hyperparameters came from
    hyperparams_source: str = ""

    def run_args(self) -> dict[str, Any]:
        """The ``args.yml`` entries that, with ``config.yml``, make two runs the same run."""
        return {
            "algo": self.algo,
            "variant": self.variant,
            "env": self.env_id,
            "seed": self.seed,
            "n_timesteps": self.n_timesteps,
            "eval_freq": self.eval_freq,
            "eval_episodes": self.n_eval_episodes,
        }

    def args(self) -> dict[str, Any]:
        """The run's ``args.yml`` (rl-zoo3's names where the zoo has one): :meth:`run_args`, then how it ran."""
        return {
            **self.run_args(),
            "num_threads": self.num_threads,
            "device": self.device,
            "hyperparams_source": self.hyperparams_source,
            "versions": package_versions(),
            **source_revision(),
            "machine": platform.machine(),
        }

    def config(self) -> dict[str, Any]:
        """The run's ``config.yml``: the hyperparameters as a zoo YAML entry, with the budget."""
        return dict(sorted({**self.hyperparams, "n_timesteps": self.n_timesteps}.items()))

    def identity(self) -> dict[str, Any]:
        """What makes two runs the same run (threads, device and versions do not)."""
        return {**self.run_args(), "config": _plain(self.config())}


#: Settings every run engine run checks before any run, whatever its algorithm: key -> (smallest allowed, integer)
COMMON_RANGES: dict[str, tuple[float, bool]] = {
    "learning_starts": (0, True),
    "batch_size": (1, True),
    "buffer_size": (1, True),
    "n_envs": (1, True),
    "n_steps": (1, True),
}


def check_run_settings(spec: "RunSpec") -> None:
    """
    Raise ``ValueError`` naming the run and the key for a budget, evaluation setting or common hyperparameter of the
    wrong type or out of range, and for ``learning_starts`` at or above the budget (the run would train nothing and
    report an untrained policy as its result).
    """
    where = f"{spec.variant} on {spec.env_id}"
    for key, value, low in (("n_timesteps", spec.n_timesteps, 1), ("eval_freq", spec.eval_freq, 1)):
        if value < low:
            raise ValueError(f"{where}: {key}={value} is out of range: it must be an integer >= {low}")
    if spec.n_eval_episodes < 1:
        raise ValueError(f"{where}: eval_episodes={spec.n_eval_episodes} is out of range: it must be an integer >= 1")
    if spec.eval_freq > spec.n_timesteps:
        raise ValueError(
            f"{where}: eval_freq={spec.eval_freq} is above the budget n_timesteps={spec.n_timesteps}: the run would "
            "never be evaluated"
        )
    for key, (smallest, integer) in COMMON_RANGES.items():
        if key not in spec.hyperparams:
            continue
        value = spec.hyperparams[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or (integer and float(value) != int(value)) or value < smallest:
            kind = "an integer" if integer else "a number"
            raise ValueError(f"{where}: {key}={value!r} is invalid: it must be {kind} >= {smallest:g}")
    learning_starts = spec.hyperparams.get("learning_starts")
    if learning_starts is not None and learning_starts >= spec.n_timesteps:
        raise ValueError(
            f"{where}: learning_starts={learning_starts} is at or above the budget n_timesteps={spec.n_timesteps}: "
            "the run would train nothing; lower learning_starts (e.g. -params learning_starts:"
            f"{max(spec.n_timesteps // 10, 1)}) or raise the budget"
        )


def make_spec(
    variant: str,
    algo: str,
    env_id: str,
    seed: int,
    n_timesteps: int,
    overrides: dict[str, Any] | None = None,
    eval_freq: int = 1000,
    n_eval_episodes: int = 5,
    num_threads: int | None = 1,
    device: str = "auto",
) -> RunSpec:
    """
    A run with the task's hyperparameters from ``hyperparams/<algo>.yml`` (see :func:`default_hyperparams`), then
    ``overrides``; ``ValueError`` for a key ``algo`` does not take.
    """
    from sb3_sera.experiments.zoo import check_algo_task

    check_algo_task(algo, env_id)
    defaults, source = default_hyperparams(algo, env_id)
    hyperparams = {**defaults, **(overrides or {})}
    hyperparams.pop("n_timesteps", None)
    check_hyperparams(algo, hyperparams, f"{variant} on {env_id}")
    spec = RunSpec(
        variant=variant,
        algo=algo,
        env_id=env_id,
        seed=int(seed),
        n_timesteps=int(n_timesteps),
        hyperparams=hyperparams,
        eval_freq=int(eval_freq),
        n_eval_episodes=int(n_eval_episodes),
        num_threads=num_threads,
        device=device,
        hyperparams_source=source,
    )
    check_run_settings(spec)
    return spec


def package_versions() -> dict[str, str]:
    """Python's and the main packages' versions."""
    import platform

    versions = {"python": platform.python_version()}
    for package in VERSIONED:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            continue
    return versions


def source_revision() -> dict[str, Any]:
    """
    The git commit of the code that runs (``git_commit``) and whether its tree was clean (``git_clean``): no tracked
    file changed, and no untracked file in the package (a log or a grid file beside the checkout does not count,
    an untracked module would): read from the repository this package is imported from; both None for an installed
    package outside a git checkout.
    """
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD") if (root / ".git").exists() else None
    if commit is None:
        return {"git_commit": None, "git_clean": None}
    status = git("status", "--porcelain", "--untracked-files=all") or ""
    package = Path(__file__).resolve().parents[1].name
    changes = [line for line in status.splitlines() if not line.startswith("??") or line[3:].startswith(f"{package}/")]
    return {"git_commit": commit.strip(), "git_clean": not changes}


class _RecordLoader(yaml.SafeLoader):
    """Safe YAML loading that also reads rl-zoo3's records, which it writes as ``OrderedDict`` objects."""


def _ordered_dict(loader: yaml.SafeLoader, node: yaml.Node) -> dict[str, Any]:
    assert isinstance(node, yaml.SequenceNode)
    (pairs,) = loader.construct_sequence(node, deep=True)
    return {key: value for key, value in pairs}


_RecordLoader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict", _ordered_dict)


def read_record(path: Path) -> dict[str, Any]:
    """One of a run's YAML records (``config.yml``, ``args.yml``), ours or rl-zoo3's."""
    return yaml.load(path.read_text(), Loader=_RecordLoader) or {}


def _plain(value: Any) -> Any:
    """``value`` as YAML round-trips it (tuples as lists), so a record compares equal to the spec it came from."""
    return yaml.safe_load(yaml.safe_dump(value))


def records_dir(folder: Path, env_id: str) -> Path:
    """Where a run keeps ``config.yml`` and ``args.yml`` (rl-zoo3: ``<run folder>/<env_name>/``)."""
    return folder / env_name(env_id)


def run_ids(variant_dir: Path, env_id: str) -> dict[int, Path]:
    """The run folders ``<env_name>_<id>`` of one task under a variant's folder, by id."""
    prefix = f"{env_name(env_id)}_"
    folders = {}
    for folder in variant_dir.glob(f"{prefix}*"):
        suffix = folder.name[len(prefix) :]
        if folder.is_dir() and suffix.isdigit():
            folders[int(suffix)] = folder
    return folders


def assign_folders(specs: Sequence[RunSpec], out_dir: str | Path) -> list[Path]:
    """
    A folder per spec: the folder of an earlier run with the same records (finished: read back; interrupted: run
    again there), else a new ``<env_name>_<id>`` with the next free id, its records written at once.
    """
    folders: list[Path] = []
    taken: set[Path] = set()
    for spec in specs:
        variant_dir = Path(out_dir) / spec.variant
        existing = run_ids(variant_dir, spec.env_id)
        match = None
        for _, folder in sorted(existing.items()):
            args_file = records_dir(folder, spec.env_id) / "args.yml"
            if folder not in taken and args_file.exists() and _same_run(folder, spec):
                match = folder
                break
        if match is None:
            next_id = max([*existing, *(_id_of(f, spec.env_id) for f in taken if f.parent == variant_dir)], default=0) + 1
            match = variant_dir / f"{env_name(spec.env_id)}_{next_id}"
            records = records_dir(match, spec.env_id)
            records.mkdir(parents=True)
            (records / "config.yml").write_text(yaml.safe_dump(_plain(spec.config()), sort_keys=True))
            (records / "args.yml").write_text(yaml.safe_dump(_plain(spec.args()), sort_keys=True))
        taken.add(match)
        folders.append(match)
    return folders


def _id_of(folder: Path, env_id: str) -> int:
    return int(folder.name[len(env_name(env_id)) + 1 :])


def _same_run(folder: Path, spec: RunSpec) -> bool:
    records = records_dir(folder, spec.env_id)
    args, config = read_record(records / "args.yml"), read_record(records / "config.yml")
    recorded = {key: args.get(key) for key in spec.run_args()}
    return {**recorded, "config": config} == spec.identity()


@dataclass
class RunResult:
    """What one finished run measured, with its records."""

    variant: str
    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    wall_time_s: float
    #: Mean return of the last evaluation
    final_return: float
    timesteps: list[int] = field(default_factory=list)
    #: Mean evaluation return at each of ``timesteps``
    returns: list[float] = field(default_factory=list)
    #: Initial-state value bias at each of ``timesteps``: mean ``V(s0)`` minus mean discounted return over the
    #: evaluation's episodes (empty for runs evaluated without :class:`InitialStateBiasCallback`)
    initial_state_bias: list[float] = field(default_factory=list)
    #: The resolved hyperparameters (``config.yml`` without the budget)
    hyperparams: dict[str, Any] = field(default_factory=dict)
    #: The run folder
    folder: str = ""
    #: Steps between evaluations and episodes per evaluation, as recorded (None: not recorded, as by rl-zoo3's train)
    eval_freq: int | None = None
    eval_episodes: int | None = None


def make_model(spec: RunSpec, env: VecEnv, tensorboard_log: str | None = None) -> BaseAlgorithm:
    """The spec's model on ``env``, its hyperparameters turned into objects as rl-zoo3 does."""
    from rl_zoo3.exp_manager import ExperimentManager

    kwargs = {key: value for key, value in spec.hyperparams.items() if key not in RUN_KEYS}
    # Schedules given as strings ("lin_3e-4") become rl-zoo3's schedule objects
    kwargs.update(ExperimentManager._preprocess_schedules({k: v for k, v in kwargs.items() if isinstance(v, str)}))
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = parse_policy_kwargs(kwargs["policy_kwargs"])
    elif isinstance(kwargs.get("policy_kwargs"), dict):
        # SB3 writes into the dict it is given (use_sde, ...): a grid's dict shared by variants must stay as written
        kwargs["policy_kwargs"] = copy.deepcopy(kwargs["policy_kwargs"])
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    noise_type = spec.hyperparams.get("noise_type")
    if noise_type is not None:
        assert isinstance(env.action_space, spaces.Box)
        n_actions = env.action_space.shape[0]
        noise_std = float(spec.hyperparams.get("noise_std", 0.1))
        noises = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}
        if noise_type not in noises:
            raise ValueError(f"noise_type={noise_type!r} is invalid: expected one of {sorted(noises)}")
        kwargs["action_noise"] = noises[noise_type](mean=np.zeros(n_actions), sigma=noise_std * np.ones(n_actions))
    policy = spec.hyperparams.get("policy", policy_for(env))
    model_class = algorithm_classes()[spec.algo]
    return model_class(policy, env, seed=spec.seed, verbose=0, device=spec.device, tensorboard_log=tensorboard_log, **kwargs)


def check_specs(specs: Sequence[RunSpec]) -> None:
    """
    Build each distinct (algorithm, task, hyperparameters) model once, without training, so that a value out of range
    (``sera_alpha=2``) or a bad ``policy_kwargs`` is refused before the first run starts: ``ValueError`` naming the run.
    """
    seen = set()
    for spec in specs:
        key = json.dumps([spec.algo, spec.env_id, spec.hyperparams], sort_keys=True, default=str)
        if key in seen:
            continue
        seen.add(key)
        env = make_vec_env(spec.env_id, n_envs=1, env_kwargs=spec.hyperparams.get("env_kwargs") or {})
        try:
            make_model(spec, env)
        except (ValueError, TypeError, KeyError, SyntaxError, NameError) as error:
            raise ValueError(f"{spec.variant} on {spec.env_id}: {type(error).__name__}: {error}") from None
        finally:
            env.close()


def policy_for(env: VecEnv) -> str:
    """``"CTDEPolicy"`` for a multi-agent CTDE task (Dict observation with a state), else ``"MlpPolicy"``."""
    space = env.observation_space
    return "CTDEPolicy" if isinstance(space, spaces.Dict) and STATE_KEY in space.spaces else "MlpPolicy"


#: Where a running run keeps its step count for the command's progress bar (removed when it ends)
PROGRESS_FILE = ".progress"


class ProgressFile(BaseCallback):
    """Writes the model's step count to a file every ``every`` calls, for the progress bar of the command."""

    def __init__(self, path: Path, every: int = 500) -> None:
        super().__init__()
        self.path, self.every = path, every

    def _on_step(self) -> bool:
        if self.n_calls % self.every == 0:
            self.path.write_text(str(self.num_timesteps))
        return True


def steps_done(folder: Path, budget: int) -> int:
    """Steps a run has made: its budget when finished, else what its progress file says (0 before it starts)."""
    if (folder / RESULT_FILE).exists():
        return budget
    try:
        return min(int((folder / PROGRESS_FILE).read_text() or 0), budget)
    except (OSError, ValueError):
        return 0


def train_one(spec: RunSpec, folder: str | Path) -> RunResult:
    """
    Train one run in its folder (made by :func:`assign_folders`), evaluating every ``spec.eval_freq`` steps; a
    finished run is read back.
    """
    folder = Path(folder)
    if (folder / RESULT_FILE).exists():
        return load_result(folder)
    route_mujoco_warnings()
    # An interrupted run starts again here, maybe under newer code: its record names the code that runs now
    (records_dir(folder, spec.env_id) / "args.yml").write_text(yaml.safe_dump(_plain(spec.args()), sort_keys=True))
    if spec.num_threads is not None:
        th.set_num_threads(spec.num_threads)
    env_kwargs = spec.hyperparams.get("env_kwargs") or {}
    n_envs = int(spec.hyperparams.get("n_envs", 1))
    env = make_vec_env(spec.env_id, n_envs=n_envs, seed=spec.seed, monitor_dir=str(folder), env_kwargs=env_kwargs)
    eval_env = make_vec_env(spec.env_id, n_envs=1, seed=spec.seed + 10_000, env_kwargs=env_kwargs)
    model = make_model(spec, env, tensorboard_log=str(folder))
    callback = InitialStateBiasCallback(
        eval_env,
        eval_freq=max(spec.eval_freq // n_envs, 1),
        n_eval_episodes=spec.n_eval_episodes,
        log_path=str(folder),
        verbose=0,
    )
    start = time.perf_counter()
    progress = ProgressFile(folder / PROGRESS_FILE)
    model.learn(spec.n_timesteps, callback=[callback, progress], tb_log_name=f"{spec.variant}_seed{spec.seed}")
    wall_time = time.perf_counter() - start
    (folder / PROGRESS_FILE).unlink(missing_ok=True)
    model.save(folder / env_name(spec.env_id))
    env.close()
    eval_env.close()
    # Written last: its presence marks the run as finished. Threads and device as the worker saw them
    result = {"wall_time_s": wall_time, "torch_threads": th.get_num_threads(), "device": str(model.device)}
    (folder / RESULT_FILE).write_text(json.dumps(result))
    return load_result(folder)


def load_result(folder: Path) -> RunResult:
    """
    A finished run of this engine or of ``sb3-sera train`` (its records, evaluations and bias records).

    :raises ValueError: naming the folder and what is wrong with its records (missing, empty, not a mapping, no
        seed or budget, unreadable or empty evaluations, an unreadable ``result.json``)
    """
    args_files = list(folder.glob("*/args.yml"))
    if not args_files:
        raise ValueError(f"{folder}: no <env_name>/args.yml record, so its seed and budget are unknown")
    records = args_files[0].parent
    try:
        args, config = read_record(records / "args.yml"), read_record(records / "config.yml")
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{folder}: unreadable record: {' '.join(str(error).split())}") from None
    for name, record in (("args.yml", args), ("config.yml", config)):
        if not isinstance(record, dict) or not record:
            raise ValueError(f"{folder}: {name} is {'empty' if not record else 'not a mapping'}")
    missing = [key for key in ("algo", "env", "seed") if args.get(key) is None]
    if missing:
        raise ValueError(f"{folder}: args.yml has no {', '.join(missing)}")
    try:
        with np.load(folder / "evaluations.npz") as evaluations:
            returns = evaluations["results"].mean(axis=1)
            timesteps = [int(t) for t in evaluations["timesteps"]]
    except NPZ_ERRORS as error:
        raise ValueError(f"{folder}: unreadable evaluations.npz ({type(error).__name__}: {error})") from None
    if len(timesteps) == 0 or len(timesteps) != len(returns):
        raise ValueError(f"{folder}: evaluations.npz holds {len(timesteps)} steps and {len(returns)} returns")
    bias: list[float] = []
    if (folder / BIAS_FILE).exists():
        try:
            with np.load(folder / BIAS_FILE) as bias_records:
                bias = initial_state_bias(bias_records["values"], bias_records["discounted_returns"])
        except NPZ_ERRORS as error:
            raise ValueError(f"{folder}: unreadable {BIAS_FILE} ({type(error).__name__}: {error})") from None
    result_file = folder / RESULT_FILE
    wall_time = math.nan
    if result_file.exists():
        try:
            wall_time = float(json.loads(result_file.read_text())["wall_time_s"])
        except (ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{folder}: unreadable {RESULT_FILE} ({type(error).__name__}: {error})") from None
    try:
        budget = int(args.get("n_timesteps") or -1)
        if budget <= 0:
            # rl-zoo3 records -1 when the budget came from the YAML entry
            budget = int(float(config["n_timesteps"]))
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{folder}: neither args.yml nor config.yml gives the budget (n_timesteps)") from None
    hyperparams = {key: value for key, value in config.items() if key != "n_timesteps"}
    eval_freq, eval_episodes = args.get("eval_freq"), args.get("eval_episodes")
    return RunResult(
        variant=str(args.get("variant") or args["algo"]),
        algo=str(args["algo"]),
        env_id=str(args["env"]),
        seed=int(args["seed"]),
        n_timesteps=budget,
        wall_time_s=wall_time,
        final_return=float(returns[-1]),
        timesteps=timesteps,
        returns=[float(r) for r in returns],
        initial_state_bias=bias,
        hyperparams=_plain(hyperparams),
        folder=str(folder),
        eval_freq=None if eval_freq is None else int(eval_freq),
        eval_episodes=None if eval_episodes is None else int(eval_episodes),
    )


def default_threads(n_jobs: int) -> int:
    """
    torch threads per run when ``n_jobs`` runs share the machine: ``OMP_NUM_THREADS`` when it is set (the user's
    word), else the cores divided among the runs, at least one.
    """
    from_env = os.environ.get("OMP_NUM_THREADS", "")
    if from_env.isdigit() and int(from_env) > 0:
        return int(from_env)
    return max((os.cpu_count() or 1) // max(n_jobs, 1), 1)


#: The lock file of an output folder, held by the command that runs into it
LOCK_FILE = ".sb3_sera.lock"


@contextmanager
def output_lock(out_dir: str | Path) -> Iterator[None]:
    """
    Hold ``<out_dir>/.sb3_sera.lock`` while runs are made into ``out_dir``: a second ``compare``/``bench`` into the
    same folder is refused with a ``RuntimeError`` naming the holder, instead of training inside the first one's
    run folders. The lock is the operating system's (``flock``): a killed holder releases it.
    """
    import fcntl

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    handle = (out / LOCK_FILE).open("a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "another process"
        handle.close()
        raise RuntimeError(f"{out} is in use by {holder}: wait for it to end, or give another --out") from None
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()} ({' '.join(sys.argv)}), since {time.strftime('%Y-%m-%d %H:%M:%S')}")
        handle.flush()
        yield
    finally:
        handle.truncate(0)
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


class Interrupted(RuntimeError):
    """Runs stopped by Ctrl-C (SIGINT) or SIGTERM: the finished ones are kept, the unfinished ones named."""


def _worker_init(parent: int) -> None:
    """
    A run worker leaves Ctrl-C to its parent (which stops every worker once) and ends when its parent does, even
    when the parent was killed outright (Linux: the kernel signals it; elsewhere a thread watches the parent).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes
        import ctypes.util

        # A C library without prctl leaves it to the thread below to end the worker
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)  # the parent died before the death signal was set

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def execute(
    specs: Sequence[RunSpec],
    out_dir: str | Path,
    n_jobs: int | None = None,
    ray_address: str | None = None,
    progress_bar: bool = True,
) -> list[RunResult]:
    """
    Run every spec in its folder (:func:`assign_folders`): on a local process pool of ``n_jobs`` workers (default:
    one per core), or as Ray tasks of one CPU each on the cluster at ``ray_address`` (``"auto"``: the one
    ``ray start`` made on this machine). Finished runs are read back, not run again. A failed run does not stop
    the others: once all have ended, ``RuntimeError`` names the failed ones. A failed run that had not evaluated
    yet leaves no folder behind; one that had keeps its logs, without the ``result.json`` of a finished run.
    ``out_dir`` is locked while the runs are made (:func:`output_lock`). One Ctrl-C (or SIGTERM) stops every
    worker and raises :class:`Interrupted` naming the unfinished runs, which the same command resumes.

    :return: the results, in the order of ``specs``
    """
    with output_lock(out_dir):
        folders = assign_folders(specs, out_dir)
        if ray_address is not None:
            outcomes = _execute_on_ray(specs, folders, ray_address, progress_bar)
        else:
            outcomes = _execute_locally(specs, folders, n_jobs, progress_bar)
    failed = []
    for spec, folder, outcome in zip(specs, folders, outcomes, strict=True):
        if isinstance(outcome, BaseException):
            failed.append(f"{spec.variant} on {spec.env_id} seed {spec.seed} ({folder}): {outcome}")
            if not (folder / "evaluations.npz").exists():
                shutil.rmtree(folder, ignore_errors=True)
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(specs)} run(s) failed: " + "; ".join(failed))
    return [outcome for outcome in outcomes if isinstance(outcome, RunResult)]


def _execute_locally(
    specs: Sequence[RunSpec], folders: Sequence[Path], n_jobs: int | None, progress_bar: bool
) -> list[RunResult | BaseException]:
    n_jobs = min(n_jobs or os.cpu_count() or 1, len(specs))
    outcomes: dict[int, RunResult | BaseException] = {}
    pool = ProcessPoolExecutor(
        max_workers=n_jobs, mp_context=get_context("spawn"), initializer=_worker_init, initargs=(os.getpid(),)
    )
    # SIGTERM (a scheduler, kill) stops the runs as Ctrl-C does (signals are the main thread's to handle)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    total = sum(spec.n_timesteps for spec in specs)
    try:
        with tqdm(total=total, desc=f"{len(specs)} runs", unit="step", disable=not progress_bar) as bar:
            futures = {
                pool.submit(train_one, spec, folder): index
                for index, (spec, folder) in enumerate(zip(specs, folders, strict=True))
            }
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=2.0, return_when=FIRST_COMPLETED)
                for future in done:
                    error = future.exception()
                    outcomes[futures[future]] = error if error is not None else future.result()
                # Steps inside the runs: each worker writes its count every few hundred steps
                steps = sum(steps_done(folder, spec.n_timesteps) for spec, folder in zip(specs, folders, strict=True))
                bar.set_postfix_str(f"{len(outcomes)}/{len(specs)} runs ended")
                bar.update(max(steps - bar.n, 0))
    except KeyboardInterrupt:
        for process in list(getattr(pool, "_processes", {}).values()):
            process.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        unfinished = [str(folder) for index, folder in enumerate(folders) if index not in outcomes]
        raise Interrupted(
            f"interrupted: {len(outcomes)} of {len(specs)} run(s) finished; {len(unfinished)} unfinished, left without "
            f"result.json in {', '.join(unfinished)}: the same command resumes them"
        ) from None
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    pool.shutdown()
    return [outcomes[index] for index in range(len(specs))]


def _execute_on_ray(
    specs: Sequence[RunSpec], folders: Sequence[Path], address: str, progress_bar: bool
) -> list[RunResult | BaseException]:
    try:
        import ray
    except ImportError as error:
        raise ImportError("--ray-address needs Ray: pip install 'sb3-sera[distributed]'") from error
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    remote_train: Any = ray.remote(num_cpus=1)(train_one)
    # Workers may start elsewhere: give them absolute folders
    pending = {
        remote_train.remote(spec, str(folder.resolve())): index
        for index, (spec, folder) in enumerate(zip(specs, folders, strict=True))
    }
    outcomes: dict[int, RunResult | BaseException] = {}
    with tqdm(total=len(specs), desc="runs (ray)", disable=not progress_bar) as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                index = pending.pop(ref)
                try:
                    outcomes[index] = ray.get(ref)
                except Exception as error:  # a failed run is reported with the others
                    outcomes[index] = error
                bar.update()
    return [outcomes[index] for index in range(len(specs))]


def check_task(env_id: str) -> None:
    """Raise ``ValueError`` for an env id Gymnasium does not know, listing this package's ids."""
    if env_id not in gym.registry:
        registered = sorted(name for name in gym.registry if name.startswith("sb3_sera/"))
        raise ValueError(f"unknown task {env_id!r}; registered ids include {registered} and Gymnasium's")
