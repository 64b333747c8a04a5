"""
SERASAC's cost against the number of critics K and of agents M, and the paper's cost model checked against it.

Two groups, each timed interleaved (train-only gradient steps, batch 256, medians over blocks):

- critics: SERASAC with K = 2, 5, 10 (Table 4 architectures, cycling) on HalfCheetah-v5, and stock SAC;
- agents: SERASAC (K = 5) with the CTDE policy on MaMuJoCo HalfCheetah 2x3 (M = 2), 6x1 (M = 6) and
  ManySegmentSwimmer 12x1 (M = 12).

The paper's model is ``O(K S C_Q + M S C_pi)``: with S fixed, the time per step should be affine in the critics'
and the actors' multiply-adds per sample. A least-squares fit ``t = a + b * critic MACs + c * actor MACs`` over
all SERASAC rows is printed beside the measurements.

    python benchmarks/scaling.py --blocks 8 --block-steps 50
"""

import argparse
from dataclasses import dataclass

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from timing import interleaved_rates, median_iqr
from torch import nn

from sb3_sera import SERASAC
from sb3_sera.common.mujoco_log import route_mujoco_warnings

CRITIC_GROUP = {"SAC": ("HalfCheetah-v5", None), **{f"K={k}": ("HalfCheetah-v5", k) for k in (2, 5, 10)}}
AGENT_GROUP = {
    "HalfCheetah 2x3 (M=2)": ("HalfCheetah", "2x3"),
    "HalfCheetah 6x1 (M=6)": ("HalfCheetah", "6x1"),
    "Swimmer 12x1 (M=12)": ("ManySegmentSwimmer", "12x1"),
}


@dataclass
class Row:
    label: str
    n_critics: int
    n_agents: int
    critic_macs: int
    actor_macs: int
    rate: float
    low: float
    high: float
    sera: bool


def multiply_adds(module: nn.Module) -> int:
    """Multiply-adds per sample of the linear layers of ``module`` (their weights' sizes)."""
    return sum(layer.weight.numel() for layer in module.modules() if isinstance(layer, nn.Linear))


def build(label: str, learning_starts: int) -> BaseAlgorithm:
    if label in CRITIC_GROUP:
        env_id, n_critics = CRITIC_GROUP[label]
        if n_critics is None:
            model: BaseAlgorithm = SAC("MlpPolicy", env_id, learning_starts=learning_starts, seed=0)
        else:
            policy_kwargs = {"n_critics": n_critics}
            model = SERASAC("MlpPolicy", env_id, learning_starts=learning_starts, seed=0, policy_kwargs=policy_kwargs)
    else:
        import gymnasium as gym

        scenario, agent_conf = AGENT_GROUP[label]
        env = gym.make("sb3_sera/MaMuJoCo-v0", scenario=scenario, agent_conf=agent_conf)
        model = SERASAC("CTDEPolicy", env, learning_starts=learning_starts, seed=0)
    model.learn(learning_starts)
    return model


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--blocks", type=int, default=8)
    parser.add_argument("--block-steps", type=int, default=50)
    parser.add_argument("--learning-starts", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=th.get_num_threads())
    args = parser.parse_args()
    th.set_num_threads(args.threads)

    rows: list[Row] = []
    for group in (CRITIC_GROUP, AGENT_GROUP):
        models = {label: build(label, args.learning_starts) for label in group}
        rates = interleaved_rates(models, "train", args.blocks, args.block_steps, batch_size=256)
        for label, model in models.items():
            critic: nn.Module = model.policy.critic  # type: ignore[assignment]
            actor: nn.Module = model.policy.actor  # type: ignore[assignment]
            n_critics = sum(1 for name, _ in critic.named_children() if name.startswith("qf"))
            n_agents = len(getattr(actor, "agents", ["single"]))
            rows.append(
                Row(
                    label,
                    n_critics,
                    n_agents,
                    multiply_adds(critic),
                    multiply_adds(actor),
                    *median_iqr(rates[label]),
                    sera=isinstance(model, SERASAC),
                )
            )

    sera = [row for row in rows if row.sera]
    design = np.array([[1.0, row.critic_macs, row.actor_macs] for row in sera])
    milliseconds = np.array([1000.0 / row.rate for row in sera])
    coefficients, *_ = np.linalg.lstsq(design, milliseconds, rcond=None)
    print(
        f"batch 256, {args.threads} torch thread(s); fit t = {coefficients[0]:.2f} ms + "
        f"{coefficients[1] * 1e6:.2f} ms/M critic MACs + {coefficients[2] * 1e6:.2f} ms/M actor MACs"
    )
    print(
        f"{'configuration':<24} {'K':>3} {'M':>3} {'critic MACs':>12} {'actor MACs':>11} {'steps/s':>8} "
        f"{'IQR':>12} {'ms/step':>8} {'model ms':>9}"
    )
    for row in rows:
        predicted = coefficients @ [1.0, row.critic_macs, row.actor_macs] if row.sera else float("nan")
        print(
            f"{row.label:<24} {row.n_critics:>3} {row.n_agents:>3} {row.critic_macs:>12,} {row.actor_macs:>11,} "
            f"{row.rate:>8.1f} {f'{row.low:.1f}-{row.high:.1f}':>12} {1000.0 / row.rate:>8.2f} {predicted:>9.2f}"
        )


if __name__ == "__main__":
    main()
