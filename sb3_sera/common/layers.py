"""
Layers shared by the ensembles: ``n_members`` same-shape linear layers (or MLPs) held as stacked weights with a
leading member dimension and run with batched matrix products, never a Python loop over members.
"""

import itertools
import math

import torch as th
from torch import nn


class BatchedLinear(nn.Module):
    """
    ``n_members`` independent linear layers ``y_m = x_m W_m + b_m``, stored as one ``(n_members, in, out)`` weight.

    Each member is initialized as ``nn.Linear`` initializes itself (weights and biases uniform in
    ``[-1/sqrt(in), 1/sqrt(in)]``).

    :param n_members: number of independent layers
    :param in_features: input size
    :param out_features: output size
    """

    def __init__(self, n_members: int, in_features: int, out_features: int):
        super().__init__()
        self.n_members = n_members
        self.in_features = in_features
        self.out_features = out_features
        bound = 1 / math.sqrt(in_features)
        self.weight = nn.Parameter(th.empty(n_members, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(th.empty(n_members, 1, out_features).uniform_(-bound, bound))

    def forward(self, inputs: th.Tensor) -> th.Tensor:
        """
        :param inputs: one input per member, shape ``(n_members, batch, in)``, or one input for all members,
            shape ``(batch, in)``
        :return: shape ``(n_members, batch, out)``
        """
        if inputs.dim() == 2:
            return th.matmul(inputs, self.weight) + self.bias
        return th.baddbmm(self.bias, inputs, self.weight)

    def extra_repr(self) -> str:
        return f"n_members={self.n_members}, in_features={self.in_features}, out_features={self.out_features}"


def batched_mlp(
    n_members: int, input_dim: int, output_dim: int, net_arch: list[int], activation_fn: type[nn.Module]
) -> nn.Sequential:
    """
    ``n_members`` independent MLPs as SB3's ``create_mlp`` builds one (no activation after the output layer).

    :param n_members: number of members
    :param input_dim: input size
    :param output_dim: output size; ``<= 0``: no output layer (the last hidden layer is the output)
    :param net_arch: hidden layer sizes
    :param activation_fn: activation after each hidden layer
    """
    layers: list[nn.Module] = []
    sizes = [input_dim, *net_arch]
    for in_size, out_size in itertools.pairwise(sizes):
        layers += [BatchedLinear(n_members, in_size, out_size), activation_fn()]
    if output_dim > 0:
        layers.append(BatchedLinear(n_members, sizes[-1], output_dim))
    return nn.Sequential(*layers)
