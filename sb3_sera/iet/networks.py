"""
The soft-modular network of IET (docs/SPEC.md, section 4): one network that holds an implicit ensemble of policies,
the latent vector choosing, through a routing network, how ``n_modules`` modules per layer are mixed.

The layout is that of the authors' ``ModularGatedCascadeCondNet`` (Yang et al. 2020's soft modularization, as IET's
code configures it: no batch normalization, latent shaped by a softmax network first):

- observation trunk ``h = W2 relu(W1 o)`` (``hidden_dim`` wide); latent shaping ``e = softmax(MLP(z))``, then
  ``g = MLP(e) * h`` (``*``: elementwise), then ``n_gating_layers`` layers on ``relu(g)``;
- routing: ``p_1 = softmax(L_1 relu(g))``, an ``(n_modules, n_modules)`` matrix per sample whose row ``j`` mixes the
  previous layer's modules into module ``j``'s input; each later matrix ``p_l`` (and the final weights ``p_last``
  over the last layer's modules) is ``softmax(L_l relu(C_l [p_1, ..., p_{l-1}] * g))``;
- modules: layer 1 reads ``relu(h)``; module ``j`` of layer ``l > 1`` reads ``relu(sum_i p_{l-1}[j, i] u_i)``; the
  output is ``relu(sum_j p_last[j] u_j)`` over the last layer's module outputs ``u``.

Each layer's modules are one :class:`~sb3_sera.common.layers.BatchedLinear` (stacked weights, batched products).
"""

import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn
from torch.nn import functional as F

from sb3_sera.common.hyperparameters import check_int
from sb3_sera.common.layers import BatchedLinear


def mix_modules(weights: th.Tensor, module_outputs: th.Tensor) -> th.Tensor:
    """
    Each next-layer module's input: ``x_j = sum_i weights[j, i] * u_i``, per sample.

    :param weights: routing matrices, shape ``(batch, M_next, M)``, rows summing to one
    :param module_outputs: the modules' outputs ``u``, shape ``(M, batch, H)``
    :return: shape ``(M_next, batch, H)``
    """
    return th.einsum("bji,ibh->jbh", weights, module_outputs)


def combine_modules(weights: th.Tensor, module_outputs: th.Tensor) -> th.Tensor:
    """
    The network's output before its last activation: ``sum_j weights[j] * u_j``, per sample.

    :param weights: final routing weights, shape ``(batch, M)``, summing to one
    :param module_outputs: the last layer's module outputs, shape ``(M, batch, H)``
    :return: shape ``(batch, H)``
    """
    return th.einsum("bj,jbh->bh", weights, module_outputs)


def routing_entropy(weights: th.Tensor) -> th.Tensor:
    """
    Mean entropy (nats) of routing distributions over their last dimension: ``log M`` when every module is weighed
    the same, 0 when one module takes everything.

    :param weights: probabilities summing to one over the last dimension, any leading shape
    """
    return -(weights * th.log(weights.clamp_min(1e-12))).sum(dim=-1).mean()


class SoftModularNetwork(nn.Module):
    """
    IET's soft-modular trunk: reads ``[observation, latent]`` (the latent last) and returns ``hidden_dim`` features.

    :param observation_dim: size of the observation part of the input
    :param latent_dim: size of the latent part (the input's last ``latent_dim`` entries)
    :param hidden_dim: width of every layer (trunk, latent networks, gating, modules); the authors' 64
    :param n_layers: module layers (at least 2, as in the authors' network); the authors' 2
    :param n_modules: modules per layer; the authors' 2
    :param n_gating_layers: layers of the gating network between the latent and the routing; the authors' 2
    """

    def __init__(
        self,
        observation_dim: int,
        latent_dim: int,
        hidden_dim: int = 64,
        n_layers: int = 2,
        n_modules: int = 2,
        n_gating_layers: int = 2,
    ):
        super().__init__()
        self.observation_dim = check_int("observation_dim", observation_dim, 1)
        self.latent_dim = check_int("latent_dim", latent_dim, 1)
        self.hidden_dim = check_int("hidden_dim", hidden_dim, 1)
        self.n_layers = check_int("n_layers", n_layers, 2)
        self.n_modules = check_int("n_modules", n_modules, 1)
        self.n_gating_layers = check_int("n_gating_layers", n_gating_layers, 1)
        size, modules = hidden_dim, n_modules
        self.observation_net = nn.Sequential(*create_mlp(observation_dim, hidden_dim, [hidden_dim], nn.ReLU))
        # The latent, shaped into a soft one-hot over latent_dim entries, then up to the trunk's width
        self.latent_shaping = nn.Sequential(*create_mlp(latent_dim, latent_dim, [size, size], nn.ReLU), nn.Softmax(-1))
        self.latent_net = nn.Sequential(*create_mlp(latent_dim, hidden_dim, [size], nn.ReLU))
        self.gating = nn.Sequential(*create_mlp(hidden_dim, hidden_dim, [size] * (n_gating_layers - 1), nn.ReLU))
        self.first_routing = nn.Linear(size, modules * modules)
        self.routing_conditions = nn.ModuleList(nn.Linear(layer * modules * modules, size) for layer in range(1, n_layers))
        self.routings = nn.ModuleList(
            [*(nn.Linear(size, modules * modules) for _ in range(n_layers - 2)), nn.Linear(size, modules)]
        )
        self.module_layers = nn.ModuleList(BatchedLinear(modules, size, size) for _ in range(n_layers))

    def routing(self, inputs: th.Tensor) -> tuple[list[th.Tensor], th.Tensor, th.Tensor]:
        """
        The routing of a batch of inputs.

        :param inputs: ``[observation, latent]`` rows, shape ``(batch, observation_dim + latent_dim)``
        :return: the ``n_layers - 1`` mixing matrices, each ``(batch, n_modules, n_modules)`` with rows summing to
            one; the final weights ``(batch, n_modules)``, summing to one; the observation trunk's output ``h``
        """
        observation, latent = inputs[:, : self.observation_dim], inputs[:, self.observation_dim :]
        trunk = self.observation_net(observation)
        gate = self.gating(F.relu(self.latent_net(self.latent_shaping(latent)) * trunk))
        batch, modules = inputs.shape[0], self.n_modules
        matrices = [F.softmax(self.first_routing(F.relu(gate)).view(batch, modules, modules), dim=-1)]
        for index, condition in enumerate(self.routing_conditions):
            previous = th.cat([matrix.flatten(1) for matrix in matrices], dim=1)
            logits = self.routings[index](F.relu(condition(previous) * gate))
            if index < len(self.routings) - 1:
                matrices.append(F.softmax(logits.view(batch, modules, modules), dim=-1))
            else:
                return matrices, F.softmax(logits, dim=-1), trunk
        raise AssertionError("n_layers >= 2 gives at least one routing condition")

    def forward(self, inputs: th.Tensor) -> th.Tensor:
        matrices, final_weights, trunk = self.routing(inputs)
        outputs = self.module_layers[0](F.relu(trunk))
        for matrix, layer in zip(matrices, self.module_layers[1:], strict=True):
            outputs = layer(F.relu(mix_modules(matrix, outputs)))
        return F.relu(combine_modules(final_weights, outputs))
