"""
What a run's checkpoint costs (``sera_study.runs.checkpoint``): its size on disk and the time to write and to
read it, for SERASAC on HalfCheetah-v5 (or ``--env``: a multi-agent task with the CTDE policy) with a replay buffer
holding ``--filled`` transitions (the buffer's contents are filled in directly: what is measured is their size, not how
they were collected). Reading includes building the environment anew and writing its saved state into it.

    OMP_NUM_THREADS=1 python benchmarks/checkpoint_cost.py                 # 300K transitions, the default buffer (1M)
    OMP_NUM_THREADS=1 python benchmarks/checkpoint_cost.py --env sb3_sera/HalfCheetah-6x1-v0 --filled 50000
"""

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_sera import SERASAC
from sera_study.runs.checkpoint import CHECKPOINT_DIR, load_checkpoint, save_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--filled", type=int, default=300_000, help="transitions in the replay buffer")
    parser.add_argument("--buffer-size", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    th.set_num_threads(1)
    warnings.filterwarnings("ignore")
    with tempfile.TemporaryDirectory() as folder:
        run = Path(folder)
        env = make_vec_env(args.env, n_envs=1, seed=0, monitor_dir=str(run))
        policy = "CTDEPolicy" if args.env.startswith("sb3_sera/") else "MlpPolicy"
        model = SERASAC(policy, env, buffer_size=args.buffer_size, learning_starts=100, batch_size=64, seed=0)
        model.learn(200)
        buffer = model.replay_buffer
        assert buffer is not None
        rng = np.random.default_rng(0)
        for name in ("observations", "next_observations", "actions", "rewards"):
            value = getattr(buffer, name)
            for array in value.values() if isinstance(value, dict) else [value]:
                array[: args.filled] = rng.standard_normal(array[: args.filled].shape).astype(array.dtype)
        buffer.pos, buffer.full = args.filled % args.buffer_size, args.filled >= args.buffer_size
        writes, reads = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            save_checkpoint(model, run, None, elapsed_s=0.0)
            writes.append(time.perf_counter() - start)
            start = time.perf_counter()
            load_checkpoint(SERASAC, run, "cpu", make_vec_env(args.env, n_envs=1, seed=0), None)
            reads.append(time.perf_counter() - start)
        files = {path.name: path.stat().st_size for path in (run / CHECKPOINT_DIR).iterdir()}
    total = sum(files.values())
    print(f"{args.env}, {args.filled:,} transitions in a buffer of {args.buffer_size:,}")
    print("| file | MB |\n|---|---|")
    for name, size in sorted(files.items()):
        print(f"| {name} | {size / 1e6:.1f} |")
    print(f"| total | {total / 1e6:.1f} |")
    print(f"write {np.median(writes):.2f} s, read {np.median(reads):.2f} s (median of {args.repeats})")


if __name__ == "__main__":
    main()
