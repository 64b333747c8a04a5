"""
Memory of a 300K-step SERASAC run against stock SAC: replay buffer, networks and peak RSS.

Each algorithm runs in its own process (peak RSS is per process): build the model with a 300K-transition buffer
on HalfCheetah-v5, write every slot of the buffer (so its pages are really resident, as at the end of a 300K-step
run), then run gradient steps. Reported: the buffer's arrays, the parameters and optimizer state, and the peak
resident set size.

    python benchmarks/memory.py --buffer-size 300000
"""

import argparse
import multiprocessing
import resource

import torch as th
from stable_baselines3 import SAC

from sb3_sera import SERASAC
from sb3_sera.common.mujoco_log import route_mujoco_warnings

MIB = 2**20


def _measure(name: str, env_id: str, buffer_size: int, gradient_steps: int, queue: multiprocessing.Queue) -> None:
    th.set_num_threads(1)
    algo = SAC if name == "SAC" else SERASAC
    model = algo("MlpPolicy", env_id, buffer_size=buffer_size, learning_starts=1000, seed=0)
    model.learn(1000)  # real transitions at the start of the buffer
    buffer = model.replay_buffer
    assert buffer is not None
    arrays = [buffer.observations, buffer.next_observations, buffer.actions, buffer.rewards, buffer.dones, buffer.timeouts]
    for array in arrays:
        array[1000:] = array[:1].copy()  # touch every page, as a full 300K-step buffer would
    buffer.pos, buffer.full = 0, True
    model.train(gradient_steps=gradient_steps, batch_size=256)
    parameters = sum(p.numel() * p.element_size() for p in model.policy.parameters())
    optimizer_state = sum(
        value.numel() * value.element_size()
        for optimizer in (model.actor.optimizer, model.critic.optimizer)
        for state in optimizer.state.values()
        for value in state.values()
        if isinstance(value, th.Tensor)
    )
    queue.put(
        {
            "name": name,
            "buffer_mib": sum(array.nbytes for array in arrays) / MIB,
            "parameters_mib": parameters / MIB,
            "optimizer_mib": optimizer_state / MIB,
            # ru_maxrss is in KiB on Linux
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        }
    )


def main() -> None:
    route_mujoco_warnings()  # MuJoCo's warnings through Python's, no MUJOCO_LOG.TXT
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--buffer-size", type=int, default=300_000)
    parser.add_argument("--gradient-steps", type=int, default=50)
    args = parser.parse_args()
    context = multiprocessing.get_context("spawn")
    rows = []
    for name in ("SAC", "SERASAC"):
        queue = context.Queue()
        process = context.Process(target=_measure, args=(name, args.env, args.buffer_size, args.gradient_steps, queue))
        process.start()
        rows.append(queue.get())
        process.join()
    print(f"{args.env}, replay buffer of {args.buffer_size} transitions (env dtypes), {args.gradient_steps} gradient steps")
    print(f"{'algorithm':<9} {'buffer MiB':>11} {'params MiB':>11} {'Adam state MiB':>15} {'peak RSS MiB':>13}")
    for row in rows:
        print(
            f"{row['name']:<9} {row['buffer_mib']:>11.1f} {row['parameters_mib']:>11.2f} "
            f"{row['optimizer_mib']:>15.2f} {row['peak_rss_mib']:>13.1f}"
        )
    print(f"SERASAC / SAC peak RSS: {rows[1]['peak_rss_mib'] / rows[0]['peak_rss_mib']:.3f}x")


if __name__ == "__main__":
    main()
