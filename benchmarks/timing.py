"""Interleaved timing of SB3 models, shared by the benchmark scripts."""

import argparse
import time
from collections.abc import Callable, Mapping
from typing import TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm

_Model = TypeVar("_Model")
_Measure = TypeVar("_Measure")


def time_block(model: BaseAlgorithm, mode: str, block_steps: int, batch_size: int | None) -> float:
    """
    Gradient steps per second of one block: ``train`` (gradient steps only, at ``batch_size``, or the model's own
    when None) or ``learn`` (env steps too). On a GPU the clock stops once the device has finished the block.
    """
    synchronize = th.cuda.synchronize if model.device.type == "cuda" else lambda: None
    synchronize()
    start = time.perf_counter()
    if mode == "train":
        size = model.batch_size if batch_size is None else batch_size  # type: ignore[attr-defined]
        model.train(gradient_steps=block_steps, batch_size=size)  # type: ignore[attr-defined]
    else:
        model.learn(block_steps, reset_num_timesteps=False)
    synchronize()
    return block_steps / (time.perf_counter() - start)


def interleaved(
    models: Mapping[str, _Model], measure: Callable[[_Model], _Measure], blocks: int, warmup_blocks: int = 2
) -> dict[str, list[_Measure]]:
    """
    ``measure(model)`` of each model over ``blocks`` rounds, the models taking turns (in alternating order) so that
    machine noise hits them alike; the first ``warmup_blocks`` rounds are not kept.
    """
    names = list(models)
    measured: dict[str, list[_Measure]] = {name: [] for name in names}
    for block in range(warmup_blocks + blocks):
        for name in names if block % 2 == 0 else reversed(names):
            value = measure(models[name])
            if block >= warmup_blocks:
                measured[name].append(value)
    return measured


def interleaved_rates(
    models: Mapping[str, BaseAlgorithm],
    mode: str,
    blocks: int,
    block_steps: int,
    batch_size: int | None,
    warmup_blocks: int = 2,
) -> dict[str, list[float]]:
    """Rates of each model over ``blocks`` timed blocks (:func:`time_block`), :func:`interleaved`."""
    return interleaved(models, lambda model: time_block(model, mode, block_steps, batch_size), blocks, warmup_blocks)


def median_iqr(values: list[float]) -> tuple[float, float, float]:
    """Median and interquartile range."""
    low, median, high = np.percentile(values, [25, 50, 75])
    return float(median), float(low), float(high)


def add_interleave_arguments(
    parser: argparse.ArgumentParser, blocks: int, block_steps: int, warmup_blocks: int, unit: str = "gradient steps"
) -> None:
    """The arguments every interleaved benchmark takes: its task, the blocks, their size, the untimed rounds first."""
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--blocks", type=int, default=blocks, help="timed blocks per model")
    parser.add_argument("--block-steps", type=int, default=block_steps, help=f"{unit} per block")
    parser.add_argument("--warmup-blocks", type=int, default=warmup_blocks, help="untimed rounds first")
    parser.add_argument("--learning-starts", type=int, default=1000)
