"""
Counting host reads: the values a program brings back from tensors to Python or NumPy. On a GPU each one makes the
host wait for the device, so a training loop that reads once per step cannot run ahead of the device.
"""

from typing import Any

import torch as th
from torch.overrides import TorchFunctionMode

#: What brings a tensor's values to Python or NumPy
READS = frozenset(
    {
        th.Tensor.item,
        th.Tensor.tolist,
        th.Tensor.numpy,
        th.Tensor.__bool__,
        th.Tensor.__float__,
        th.Tensor.__int__,
        th.Tensor.__index__,
    }
)


class HostReads(TorchFunctionMode):
    """
    Counts the host reads (:data:`READS`: ``item``, ``tolist``, ``numpy``, ``bool``/``float``/``int`` of a tensor)
    made while it is active, compiled code's included where it calls back into Python. On a CPU it counts the reads
    a GPU would wait on::

        with HostReads() as reads:
            model.learn(400, reset_num_timesteps=False)
        print(reads.count / 400, "host reads per env step")
    """

    def __init__(self) -> None:
        super().__init__()
        #: Host reads so far
        self.count = 0

    def __torch_function__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        if func in READS:
            self.count += 1
        return func(*args, **(kwargs or {}))
