"""Volume rendering math on hard numbers (fields/rendering.py)."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fields.rendering import (
    accumulate,
    alpha_from_density,
    composite,
    distortion_loss,
    opacity,
    transmittance,
    weights_from_density,
)


def test_zero_density_gives_zero_weights_and_full_transmittance():
    sigma = torch.zeros(4, 8)
    deltas = torch.full((4, 8), 0.5)
    w = weights_from_density(sigma, deltas)
    assert torch.equal(w, torch.zeros_like(w))
    assert torch.equal(transmittance(sigma, deltas), torch.ones_like(w))


def test_huge_density_puts_all_weight_on_first_sample():
    sigma = torch.full((2, 5), 1e9)
    deltas = torch.full((2, 5), 0.1)
    w = weights_from_density(sigma, deltas)
    assert torch.isfinite(w).all()
    assert torch.allclose(w[:, 0], torch.ones(2))
    assert torch.allclose(w[:, 1:], torch.zeros(2, 4))


def test_zero_length_intervals_are_transparent_even_with_huge_density():
    sigma = torch.tensor([[1e9, 1e9, 1.0]])
    deltas = torch.tensor([[0.0, 0.0, 1.0]])
    w = weights_from_density(sigma, deltas)
    assert torch.allclose(w, torch.tensor([[0.0, 0.0, 1 - math.exp(-1)]]))


def test_open_last_interval_absorbs_the_rest():
    sigma = torch.tensor([[0.5, 0.5, 0.5]])
    deltas = torch.tensor([[1.0, 1.0, math.inf]])
    w = weights_from_density(sigma, deltas)
    assert torch.isfinite(w).all()
    assert abs(float(w.sum()) - 1.0) < 1e-6


def test_open_last_interval_with_zero_density_is_not_nan():
    w = weights_from_density(torch.zeros(1, 3), torch.tensor([[1.0, 1.0, math.inf]]))
    assert torch.equal(w, torch.zeros(1, 3))


def test_nan_and_negative_density_count_as_empty():
    w = weights_from_density(torch.tensor([[math.nan, -5.0, 1.0]]), torch.ones(1, 3))
    assert torch.isfinite(w).all()
    assert w[0, 0] == 0 and w[0, 1] == 0


def test_tiny_optical_depth_uses_expm1_precision():
    a = alpha_from_density(torch.tensor([1e-10], dtype=torch.float32), torch.tensor([1e-3]))
    assert abs(float(a) - 1e-13) / 1e-13 < 1e-4


def test_gradients_finite_at_extremes():
    sigma = torch.tensor([[0.0, 1e9, 1e-8, 3.0, 1e9]], requires_grad=True)
    deltas = torch.tensor([[0.0, 0.0, 1.0, math.inf, 1.0]])
    rgb = torch.rand(1, 5, 3)
    out = composite(weights_from_density(sigma, deltas), rgb, torch.ones(3))
    out.sum().backward()
    assert torch.isfinite(sigma.grad).all()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0, 1e12, allow_nan=False), min_size=1, max_size=16),
       st.lists(st.floats(0, 1e3, allow_nan=False), min_size=16, max_size=16))
def test_accumulated_opacity_at_most_one(sig, dl):
    sigma = torch.tensor([sig], dtype=torch.float32)
    deltas = torch.tensor([dl[: len(sig)]], dtype=torch.float32)
    w = weights_from_density(sigma, deltas)
    assert torch.isfinite(w).all()
    assert (w >= 0).all()
    assert float(w.sum()) <= 1.0 + 1e-5
    assert float(opacity(w)) <= 1.0


def test_composite_with_background():
    w = torch.tensor([[0.25, 0.25]])
    rgb = torch.tensor([[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    out = composite(w, rgb, torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(out, torch.tensor([[0.5, 0.0, 0.5]]))
    assert torch.allclose(accumulate(w, rgb), torch.tensor([[0.5, 0.0, 0.0]]))


def test_distortion_loss_matches_brute_force_and_prefers_concentrated_weights():
    torch.manual_seed(0)
    edges = torch.sort(torch.rand(3, 9), dim=-1).values
    w = torch.rand(3, 8) / 8
    mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
    width = edges[:, 1:] - edges[:, :-1]
    brute = (w[:, :, None] * w[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()).sum((1, 2))
    brute = brute + (w * w * width).sum(-1) / 3
    assert torch.allclose(distortion_loss(w, edges), brute, atol=1e-6)
    edges = torch.linspace(0, 1, 9).expand(1, 9)
    spread = torch.full((1, 8), 1 / 8)
    peak = torch.zeros(1, 8)
    peak[0, 3] = 1.0
    assert float(distortion_loss(peak, edges)) < float(distortion_loss(spread, edges))
