from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from gsavatar.models.mlp import AnchorMLPs, anchor_mlp_forward


def _loop_forward(x, weights, biases):
    """Reference: a Python loop of nn.functional.linear per anchor. x [B, A, in] -> [B, A, out]"""
    outs = []
    for a in range(x.shape[1]):
        h = x[:, a]
        for i, (W, b) in enumerate(zip(weights, biases)):
            h = F.linear(h, W[a].T, b[a])
            if i < len(weights) - 1:
                h = torch.relu(h)
        outs.append(h)
    return torch.stack(outs, dim=1)


def test_batched_equals_per_anchor_loop_forward_and_grads():
    torch.manual_seed(0)
    mlp = AnchorMLPs(5, 7, 4, (6, 5), generator=torch.Generator().manual_seed(1)).double()
    x = torch.randn(3, 5, 7, dtype=torch.float64, requires_grad=True)
    g = torch.randn(3, 5, 4, dtype=torch.float64)
    params = list(mlp.weights) + list(mlp.biases)

    out = mlp(x)
    grads = torch.autograd.grad((out * g).sum(), [x, *params])
    ref = _loop_forward(x, list(mlp.weights), list(mlp.biases))
    ref_grads = torch.autograd.grad((ref * g).sum(), [x, *params])

    assert out.shape == (3, 5, 4)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_anchors_are_independent():
    mlp = AnchorMLPs(4, 3, 2, (8,)).double()
    x = torch.randn(2, 4, 3, dtype=torch.float64)
    y = x.clone()
    y[:, 2] += 1.0
    a, b = mlp(x), mlp(y)
    assert torch.equal(a[:, [0, 1, 3]], b[:, [0, 1, 3]])
    assert not torch.equal(a[:, 2], b[:, 2])


def test_init_like_linear_and_scaled_last_layer():
    mlp = AnchorMLPs(10, 16, 4, (32, 8), out_init_scale=1e-3)
    assert [tuple(w.shape) for w in mlp.weights] == [(10, 16, 32), (10, 32, 8), (10, 8, 4)]
    assert [tuple(b.shape) for b in mlp.biases] == [(10, 32), (10, 8), (10, 4)]
    for W, d_in in ((mlp.weights[0], 16), (mlp.weights[1], 32)):
        bound = 1 / math.sqrt(d_in)
        assert W.abs().max() <= bound and W.abs().max() > 0.8 * bound
    assert mlp.weights[2].abs().max() <= 1e-3 / math.sqrt(8)
    assert mlp.biases[2].abs().max() <= 1e-3 / math.sqrt(8)


def test_stateless_forward_and_shape_errors():
    mlp = AnchorMLPs(3, 2, 2, (4,))
    x = torch.randn(1, 3, 2)
    assert torch.equal(mlp(x), anchor_mlp_forward(x, list(mlp.weights), list(mlp.biases)))
    with pytest.raises(ValueError, match=r"x must be \[B, 3, 2\]"):
        mlp(torch.randn(1, 4, 2))
    with pytest.raises(ValueError):
        AnchorMLPs(0, 2, 2, (4,))


def test_he_init_keeps_unit_scale_where_linear_init_shrinks_it():
    """The reason for ``mlp_init="he"``: through 3 hidden ReLU layers nn.Linear's init maps unit-variance
    inputs to outputs of std ~0.03 (the ``<w, ΔΛ>`` product then learns ~30x slower); He init keeps ~1."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(256, 6, 40, generator=g)
    stds = {}
    for init in ("linear", "he"):
        m = AnchorMLPs(6, 40, 32, (128, 128, 128), generator=torch.Generator().manual_seed(1), init=init)
        with torch.no_grad():
            stds[init] = float((m(x) - m(torch.zeros(1, 6, 40))).std())
    assert 0.7 < stds["he"] < 1.4
    assert stds["linear"] < 0.1
    he = AnchorMLPs(6, 40, 32, (128,), init="he")
    assert float(he.biases[0].detach().abs().max()) == 0.0
    assert (
        abs(float(he.weights[0].detach().std()) - (2.0 / 40) ** 0.5) < 0.02
    )  # U(-sqrt(6/in), sqrt(6/in)): std sqrt(2/in)
    with pytest.raises(ValueError, match="init"):
        AnchorMLPs(6, 40, 32, (8,), init="xavier")
