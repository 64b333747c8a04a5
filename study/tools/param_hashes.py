"""
Code identity: a hash of what each trained configuration's code computes, so that runs made at different commits are
pooled only where their code trains the same.

For every configuration in the ledger (a variant on a task with its recorded hyperparameters, ``config.yml``), a
seeded run at those settings, evaluated as the ledger's runs are: seed 0, one torch thread, ``learning_starts``
lowered to 256 and the replay buffer to 10,000 (neither changes the update's arithmetic before the buffer wraps),
2,300 environment steps, so over 2,000 gradient steps through every branch the configuration takes (its aggregation,
the adaptive or fixed critic rate, the CTDE step, delayed actor updates, action noise), with the run engine's
evaluation callback every 1,150 steps (one episode, and every recorder: the initial-state bias and the critic
diagnostics, whose replay-buffer draws the training then goes on from). The hash is SHA-256 (16 hex digits) of the
policy's parameters and buffers, of every optimizer's state, and of every array the evaluations wrote. Two commits that
print the same hash for a configuration train and evaluate it identically on this machine with these package
versions.

    OMP_NUM_THREADS=1 python study/tools/param_hashes.py                      # the working tree, every configuration
    OMP_NUM_THREADS=1 python study/tools/param_hashes.py --ledger-commits     # the ledger's commits as well
    OMP_NUM_THREADS=1 python study/tools/param_hashes.py --ledger-commits --jobs 2 --write results/code_hashes.yml
    OMP_NUM_THREADS=1 python study/tools/param_hashes.py --ledger-commits --new-commits --write results/code_hashes.yml

``--ledger-commits`` checks out every commit the ledger's runs name into a temporary git worktree and hashes there
(this script, run against that commit's package). ``--write`` stores the table in the ledger, where the report reads
it to flag a group whose runs' code trains differently (``sera_study.results.identity``). ``--new-commits`` adds
to that table only what it lacks (after new runs: a configuration at a commit it had not run at), so that adding a
run does not hash the whole ledger again.
"""

import argparse
import ast
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml

ROOT = Path(__file__).resolve().parents[2]
#: Keys of a zoo entry that describe the run, not the algorithm's constructor
RUN_KEYS = ("n_timesteps", "policy", "n_envs", "env_kwargs", "noise_type", "noise_std")
#: The short run's schedule
LEARNING_STARTS, BUFFER_SIZE, STEPS, EVAL_FREQ = 256, 10_000, 2_300, 1_150
#: The recorders' files the hash covers (the run engine's names)
EVALUATION_FILES = ("evaluations.npz", "initial_state_bias.npz", "critic_diagnostics.npz")


def configurations(ledger: Path) -> dict[str, dict[str, Any]]:
    """Every distinct (variant, task, hyperparameters) of the ledger by its key, with the commits that ran it."""
    from sera_study.results.identity import configuration_key

    found: dict[str, dict[str, Any]] = {}
    for args_file in sorted(ledger.glob("*/*/*/args.yml")):
        args = yaml.safe_load(args_file.read_text())
        config = yaml.safe_load((args_file.parent / "config.yml").read_text())
        key = configuration_key(args["variant"], args["env"], config)
        entry = found.setdefault(key, {"algo": args["algo"], "env": args["env"], "config": config, "commits": []})
        if args.get("git_commit") and args["git_commit"] not in entry["commits"]:
            entry["commits"].append(args["git_commit"])
    return found


def literal(value: Any) -> Any:
    """A zoo value: ``dict(net_arch=[256, 256])`` and other literals parsed without evaluating code."""
    if not isinstance(value, str):
        return value

    def convert(node: ast.AST) -> Any:
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict" and not node.args:
            return {keyword.arg: convert(keyword.value) for keyword in node.keywords}
        return ast.literal_eval(node)

    try:
        return convert(ast.parse(value, mode="eval").body)
    except (SyntaxError, ValueError):
        return value


def state_hash(model: Any, evaluations: Path | None = None) -> str:
    """
    SHA-256 (16 hex digits) of the policy's parameters and buffers, then of every optimizer's state, then of every
    array of the evaluation files in ``evaluations`` (a file a commit did not write is named as missing).
    """
    digest = hashlib.sha256()

    def update(name: str, value: Any) -> None:
        digest.update(name.encode())
        if isinstance(value, th.Tensor):
            digest.update(value.detach().cpu().contiguous().numpy().tobytes())
        else:
            digest.update(repr(value).encode())

    for name, tensor in model.policy.state_dict().items():
        update(name, tensor)
    for module_name in ("actor", "critic"):
        optimizer = getattr(getattr(model.policy, module_name, None), "optimizer", None)
        if optimizer is not None:
            for index, state in optimizer.state_dict()["state"].items():
                for key, value in state.items():
                    update(f"{module_name}.{index}.{key}", value)
    for path in [evaluations / name for name in EVALUATION_FILES] if evaluations is not None else []:
        if not path.exists():
            update(path.name, "missing")
            continue
        with np.load(path) as arrays:
            for key in sorted(arrays.files):
                update(f"{path.name}.{key}", th.from_numpy(np.ascontiguousarray(arrays[key])))
    return digest.hexdigest()[:16]


def hash_configuration(algo: str, env_id: str, config: dict[str, Any]) -> str:
    """The short seeded run of one configuration (see the module's docstring) and its hash."""
    import gymnasium as gym
    from rl_zoo3.utils import ALGOS
    from stable_baselines3.common.noise import NormalActionNoise

    import sb3_sera
    from sera_study.runs.zoo import ZOO_ALGOS

    assert Path(sb3_sera.__file__).resolve().is_relative_to(Path(os.environ.get("HASH_TREE", ROOT)).resolve())
    kwargs = {key: literal(value) for key, value in config.items() if key not in RUN_KEYS}
    kwargs.update(learning_starts=LEARNING_STARTS, buffer_size=BUFFER_SIZE)
    env = gym.make(env_id)
    if config.get("noise_type") is not None:
        if config["noise_type"] != "normal":
            raise ValueError(f"{algo} on {env_id}: noise_type {config['noise_type']!r} is not hashed here")
        assert isinstance(env.action_space, gym.spaces.Box)
        n_actions = env.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(
            np.zeros(n_actions), float(config.get("noise_std", 0.1)) * np.ones(n_actions)
        )
    model = {**ALGOS, **ZOO_ALGOS}[algo](config.get("policy", "MlpPolicy"), env, seed=0, device="cpu", **kwargs)
    with tempfile.TemporaryDirectory() as folder:
        model.learn(STEPS, callback=evaluation_callback(env_id, Path(folder)))
        return state_hash(model, Path(folder))


def evaluation_callback(env_id: str, folder: Path) -> Any:
    """The run engine's evaluation callback with every recorder, from wherever the hashed commit keeps it."""
    from stable_baselines3.common.env_util import make_vec_env

    try:
        from sb3_sera.common.evaluation import InitialStateBiasCallback
    except ImportError:  # commits before the module moved
        from sb3_sera.common.callbacks import InitialStateBiasCallback  # type: ignore[no-redef]
    eval_env = make_vec_env(env_id, n_envs=1, seed=10_000)
    return InitialStateBiasCallback(eval_env, eval_freq=EVAL_FREQ, n_eval_episodes=1, log_path=str(folder), verbose=0)


def hash_tree(tree: Path, found: dict[str, dict[str, Any]]) -> dict[str, str]:
    """Every configuration hashed with the package of ``tree``: this script in a child process, fed on stdin."""
    done = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child"],
        cwd=tree,
        input=json.dumps(found),
        env={**os.environ, "PYTHONPATH": str(tree), "HASH_TREE": str(tree), "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"hashing at {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def hash_commit(commit: str, found: dict[str, dict[str, Any]]) -> dict[str, str]:
    """:func:`hash_tree` at ``commit`` (a temporary git worktree), or of the working tree for ``"working tree"``."""
    if commit == "working tree":
        return hash_tree(ROOT, found)
    with tempfile.TemporaryDirectory() as folder:
        tree = Path(folder) / "tree"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), commit], check=True, capture_output=True
        )
        try:
            return hash_tree(tree, found)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=True)


def table_header() -> dict[str, Any]:
    """What a hash depends on besides the code: the short run's settings and the versions that ran it."""
    return {
        "settings": {
            "steps": STEPS,
            "learning_starts": LEARNING_STARTS,
            "buffer_size": BUFFER_SIZE,
            "eval_freq": EVAL_FREQ,
            "eval_episodes": 1,
            "threads": 1,
        },
        "versions": {"torch": str(th.__version__), "python": sys.version.split()[0]},
    }


def kept_columns(path: Path) -> dict[str, dict[str, str]]:
    """
    The hashes of a table written before (``--write``), per commit, where it was made with this script's settings
    and these versions; ``SystemExit`` where it was not.
    """
    if not path.exists():
        return {}
    table = yaml.safe_load(path.read_text()) or {}
    if {key: table.get(key) for key in ("settings", "versions")} != table_header():
        raise SystemExit(f"{path} was made with other settings or versions: hash every commit again (no --new-commits)")
    return {str(commit): dict(column) for commit, column in (table.get("hashes") or {}).items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ledger", default=str(ROOT / "results"), help="the ledger whose configurations are hashed")
    parser.add_argument("--ledger-commits", action="store_true", help="also hash at every commit the ledger names")
    parser.add_argument("--write", default=None, help="store the table (YAML) here: the ledger's code_hashes.yml")
    parser.add_argument("--jobs", type=int, default=1, help="trees hashed at a time (one core each)")
    parser.add_argument(
        "--new-commits",
        action="store_true",
        help="with --ledger-commits and --write: keep the --write table's hashes and add only those it lacks, each "
        "configuration at the commits it ran at (no working-tree column); the table must have been made with the "
        "same settings and versions",
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        # One commit's package: the configurations come on stdin, the hashes go out as one JSON line
        th.set_num_threads(1)
        warnings.filterwarnings("ignore")
        found = json.loads(sys.stdin.read())
        print(json.dumps({key: hash_configuration(e["algo"], e["env"], e["config"]) for key, e in found.items()}))
        return
    found = configurations(Path(args.ledger))
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    trees = ["working tree"]
    if args.ledger_commits:
        trees += sorted({commit for entry in found.values() for commit in entry["commits"]})
    # Per tree, the configurations to hash there: every one, or with --new-commits those that ran there unhashed
    kept: dict[str, dict[str, str]] = {}
    todo = {tree: found for tree in trees}
    if args.new_commits and args.write:
        kept = kept_columns(Path(args.write))
        todo = {
            tree: {k: e for k, e in found.items() if tree in e["commits"] and k not in kept.get(tree, {})}
            for tree in trees[1:]
        }
        todo = {tree: configurations for tree, configurations in todo.items() if configurations}
    # One child process per tree, --jobs at a time (each one torch thread)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        hashed = dict(zip(todo, pool.map(lambda tree: hash_commit(tree, todo[tree]), todo), strict=True))
    columns = {tree: {**kept.get(tree, {}), **hashed.get(tree, {})} for tree in [*trees, *kept]}
    columns = {tree: column for tree, column in columns.items() if column}
    print(f"working tree: {head[:10]}; {STEPS} steps, learning_starts {LEARNING_STARTS}, eval every {EVAL_FREQ}, one thread")
    print("| configuration | " + " | ".join(name[:10] for name in columns) + " |")
    print("|---|" + "---|" * len(columns))
    for key, entry in found.items():
        # A commit the configuration ran at is marked *
        cells = [f"{column.get(key, '-')}{' *' if name in entry['commits'] else ''}" for name, column in columns.items()]
        print(f"| {key} | " + " | ".join(cells) + " |")
    if args.write:
        table = {
            **table_header(),
            "hashes": {commit: column for commit, column in columns.items() if commit != "working tree"},
        }
        Path(args.write).write_text(yaml.safe_dump(table, sort_keys=True))
        print(f"written: {args.write}")


if __name__ == "__main__":
    main()
