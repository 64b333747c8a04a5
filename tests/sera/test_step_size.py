"""The variance-adaptive step size against hand-computed values (SPEC section 1, step 6)."""

import pytest
import torch as th

from sb3_sera.sera.step_size import (
    VarianceAdaptiveStepSize,
    batch_variance,
    critic_learning_rates,
    ema,
    kalman_gain,
)


def test_batch_variance_is_population_variance():
    # mean 2.5, squared deviations 2.25, 0.25, 0.25, 2.25 -> 5 / 4
    assert batch_variance(th.tensor([1.0, 2.0, 3.0, 4.0])).item() == pytest.approx(1.25)


def test_ema_starts_from_first_value():
    assert ema(th.tensor(0.0), th.tensor(4.0), 0.9, th.tensor(False)).item() == pytest.approx(4.0)
    assert ema(th.tensor(4.0), th.tensor(2.0), 0.9, th.tensor(True)).item() == pytest.approx(3.8)


def test_kalman_gain_and_learning_rate_range():
    assert kalman_gain(th.tensor(3.0), th.tensor(1.0), 0.0).item() == pytest.approx(0.75)
    assert kalman_gain(th.tensor(0.0), th.tensor(0.0), 1e-8).item() == 0.0
    rates = critic_learning_rates(th.tensor([0.0, 0.5, 1.0]), lr_max=5e-4, kappa_min=0.2)
    assert rates.tolist() == pytest.approx([1e-4, 3e-4, 5e-4])
    kappa = kalman_gain(th.rand(1000) * 10, th.rand(1000) * 10)
    assert ((kappa >= 0) & (kappa < 1)).all()
    rates = critic_learning_rates(kappa)  # SERASAC's default critic_lr_max, 1e-3
    assert ((rates >= 2e-4 - 1e-12) & (rates <= 1e-3 + 1e-12)).all()


def test_state_updates_by_hand():
    step_size = VarianceAdaptiveStepSize(2, td_variance_ema=0.9, estimation_variance_ema=0.9, kappa_eps=1e-8, lr_max=5e-4)
    # Batch 1: TD-error variances (1.25, 1.0), target deviation variances (0.25, 0.0)
    td_errors = th.tensor([[1.0, 0.0], [2.0, 0.0], [3.0, 2.0], [4.0, 2.0]])
    deviations = th.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    first = step_size.compute(td_errors, deviations)
    # Both averages start from the first batch: v = P = (1.25, 1.0)
    assert first.td_error_var.tolist() == pytest.approx([1.25, 1.0])
    assert first.estimation_var.tolist() == pytest.approx([1.25, 1.0])
    assert first.measurement_var.tolist() == pytest.approx([0.25, 0.0])
    assert first.kappa.tolist() == pytest.approx([1.25 / 1.5, 1.0], abs=1e-6)
    assert first.learning_rates.tolist() == pytest.approx([5e-4 * (0.2 + 0.8 * 1.25 / 1.5), 5e-4], abs=1e-9)
    # compute() has no side effect; commit() stores the averages
    assert not step_size.initialized
    assert step_size.td_error_var.tolist() == [0.0, 0.0]
    step_size.commit(first)
    assert step_size.initialized
    # Batch 2: TD-error variances (2.25, 0.0)
    second = step_size.compute(th.tensor([[0.0, 1.0], [0.0, 1.0], [3.0, 1.0], [3.0, 1.0]]), th.zeros(4, 2))
    # v = 0.9 * (1.25, 1.0) + 0.1 * (2.25, 0.0) = (1.35, 0.9); P = 0.9 * (1.25, 1.0) + 0.1 * v = (1.26, 0.99)
    assert second.td_error_var.tolist() == pytest.approx([1.35, 0.9])
    assert second.estimation_var.tolist() == pytest.approx([1.26, 0.99])
    assert second.kappa.tolist() == pytest.approx([1.0, 1.0], abs=1e-6)


def test_state_is_in_the_state_dict():
    step_size = VarianceAdaptiveStepSize(3)
    step_size.commit(step_size.compute(th.randn(8, 3), th.randn(8, 3)))
    restored = VarianceAdaptiveStepSize(3)
    restored.load_state_dict(step_size.state_dict())
    assert th.equal(restored.td_error_var, step_size.td_error_var)
    assert th.equal(restored.estimation_var, step_size.estimation_var)
    assert restored.initialized
