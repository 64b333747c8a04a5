"""
Parameter hashes of a short seeded run of every algorithm of the package: a restructuring that keeps what the
algorithms compute must print the same hashes before and after (on the same machine and versions).

    OMP_NUM_THREADS=1 python benchmarks/param_hashes.py            # one line per algorithm: name, steps, hash
    OMP_NUM_THREADS=1 python benchmarks/param_hashes.py --steps 600

Each run: seed 0, one torch thread, ``learning_starts=100``, small batches, the policy's and (where it has one) the
optimizers' state hashed with SHA-256 (first 16 hex digits), after ``--steps`` environment steps.
"""

import argparse
import hashlib
import warnings
from collections.abc import Callable
from typing import Any

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_sera import ACE, IET, MADDPG, MAPPO, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.common.mujoco_log import route_mujoco_warnings

#: The runs: name -> a function building the seeded model
RUNS: dict[str, Callable[[], BaseAlgorithm]] = {
    "SERASAC HalfCheetah-v5": lambda: SERASAC("MlpPolicy", "HalfCheetah-v5", seed=0, learning_starts=100, batch_size=64),
    "SERASAC SimpleSpread": lambda: SERASAC(
        "CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=100, batch_size=64
    ),
    "MASAC SimpleSpread": lambda: MASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=100, batch_size=64),
    "MATD3 SimpleSpread": lambda: MATD3("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=100, batch_size=64),
    "MADDPG SimpleSpread": lambda: MADDPG(
        "CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=100, batch_size=64
    ),
    "MAPPO SimpleSpread": lambda: MAPPO("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, n_steps=128, batch_size=64),
    "IET SimpleSpread": lambda: IET("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, learning_starts=100, batch_size=64),
    "SUNRISE Pendulum-v1": lambda: SUNRISE("MlpPolicy", "Pendulum-v1", seed=0, learning_starts=100, batch_size=64),
    "ACE Pendulum-v1": lambda: ACE("MlpPolicy", "Pendulum-v1", seed=0, learning_starts=100, batch_size=64),
}


def state_hash(model: BaseAlgorithm) -> str:
    """SHA-256 (16 hex digits) of the policy's parameters and buffers, then of every optimizer's state."""
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
    return digest.hexdigest()[:16]


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=400, help="environment steps of each run")
    args = parser.parse_args()
    th.set_num_threads(1)
    warnings.filterwarnings("ignore")
    for name, make in RUNS.items():
        model = make()
        model.learn(args.steps)
        print(f"{name:<24} {args.steps:>5} {state_hash(model)}")


if __name__ == "__main__":
    main()
