"""
Correlations of an ensemble's columns (one per critic) over a batch: SERA's diagnostics in its gradient step
(:mod:`sb3_sera.sera.aggregation`) and the evaluations' critic diagnostics of every algorithm
(:mod:`sb3_sera.common.evaluation`) share them, so that a baseline's runs depend on this code and not on SERA's.
"""

import torch as th


def correlation_matrix(values: th.Tensor) -> th.Tensor:
    """
    Pearson correlation of the columns of ``values`` over its rows (the batch), shape ``(K, K)``.

    A column that is constant over the batch has no defined correlation: its entries count as zero.

    Computed as ``torch.corrcoef`` computes it, operation for operation (the same values), but without its checks on
    the data, so that the compiled gradient step traces it.

    :param values: one column per critic, shape ``(batch_size, n_critics)``
    """
    columns = values.T
    centered = columns - columns.mean(dim=1, keepdim=True)
    covariance = centered @ centered.T / (columns.shape[1] - 1)
    std = covariance.diagonal().sqrt()
    return th.nan_to_num((covariance / std[:, None] / std[None, :]).clamp(-1, 1), nan=0.0)


def mean_off_diagonal(matrix: th.Tensor) -> th.Tensor:
    """Mean of the off-diagonal entries of a square ``(K, K)`` matrix, ``K >= 2``."""
    n = matrix.shape[0]
    return (matrix.sum() - matrix.diagonal().sum()) / (n * (n - 1))
