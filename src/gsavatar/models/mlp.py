"""One small MLP per anchor, all evaluated at once (stacked weights, batched matmul).

Layer ``l`` of anchor ``a`` is ``y = x @ W[l][a] + b[l][a]`` with ``W[l]`` of shape
``[A, in, out]`` (note: *input-major*, the transpose of ``nn.Linear.weight``) and
``b[l]`` of shape ``[A, out]``; ReLU between layers, none after the last. Evaluated
as one ``torch.baddbmm`` per layer with the anchor dimension as the batch dimension.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def anchor_mlp_forward(x: Tensor, weights: list[Tensor], biases: list[Tensor]) -> Tensor:
    """Stateless forward of the stacked per-anchor MLPs.

    Args:
        x: Tensor  # [B, A, in]
        weights: per layer  # [A, in_l, out_l]
        biases: per layer  # [A, out_l]

    Returns:
        Tensor  # [B, A, out]
    """
    h = x.transpose(0, 1)  # [A, B, in]: anchors as the bmm batch
    last = len(weights) - 1
    for i, (W, b) in enumerate(zip(weights, biases)):
        h = torch.baddbmm(b[:, None, :], h, W)  # [A, B, out_l]
        if i < last:
            h = torch.relu(h)
    return h.transpose(0, 1)  # [B, A, out]


class AnchorMLPs(nn.Module):
    """``A`` independent MLPs ``in_dim -> hidden... -> out_dim`` with stacked weights.

    Init (``init``):

    - ``"linear"``: every anchor's layer as ``nn.Linear`` (kaiming-uniform weights with ``a=sqrt(5)``,
      i.e. ``U(-1/sqrt(in), 1/sqrt(in))`` for weights and biases). Each ReLU layer then shrinks the
      signal's std by ~0.4, so four layers map unit-variance inputs to outputs of std ~0.01.
    - ``"he"``: variance-preserving: hidden weights ``U(-sqrt(6/in), sqrt(6/in))`` (He, for ReLU), last
      layer ``U(-sqrt(3/in), sqrt(3/in))`` (unit gain), biases 0: unit-variance inputs give outputs of
      std ~1 at any depth.

    The last layer's weights and bias are multiplied by ``out_init_scale``.
    """

    def __init__(
        self,
        num_anchors: int,
        in_dim: int,
        out_dim: int,
        hidden: tuple[int, ...] | list[int],
        out_init_scale: float = 1.0,
        generator: torch.Generator | None = None,
        init: str = "linear",
    ) -> None:
        super().__init__()
        if init not in ("linear", "he"):
            raise ValueError(f"init must be 'linear' or 'he', got {init!r}")
        if num_anchors <= 0 or in_dim <= 0 or out_dim <= 0:
            raise ValueError(f"num_anchors, in_dim, out_dim must be > 0, got {num_anchors}, {in_dim}, {out_dim}")
        self.num_anchors = int(num_anchors)
        self.in_dim = int(in_dim)
        self.out_dim = int(out_dim)
        self.hidden = tuple(int(h) for h in hidden)
        dims = (self.in_dim, *self.hidden, self.out_dim)
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
            last = i == len(dims) - 2
            s = out_init_scale if last else 1.0
            if init == "linear":
                bound = b_bound = 1.0 / math.sqrt(d_in)  # nn.Linear's init for both weight and bias
            else:
                bound, b_bound = math.sqrt((3.0 if last else 6.0) / d_in), 0.0
            W = (torch.rand(num_anchors, d_in, d_out, generator=generator) * 2 - 1) * (bound * s)
            b = (torch.rand(num_anchors, d_out, generator=generator) * 2 - 1) * (b_bound * s)
            self.weights.append(nn.Parameter(W))  # [A, in, out]
            self.biases.append(nn.Parameter(b))  # [A, out]

    @property
    def num_layers(self) -> int:
        return len(self.weights)

    def forward(self, x: Tensor) -> Tensor:
        """x: Tensor  # [B, A, in] -> Tensor  # [B, A, out]"""
        if x.ndim != 3 or x.shape[1] != self.num_anchors or x.shape[2] != self.in_dim:
            raise ValueError(f"x must be [B, {self.num_anchors}, {self.in_dim}], got {tuple(x.shape)}")
        return anchor_mlp_forward(x, list(self.weights), list(self.biases))

    def extra_repr(self) -> str:
        return f"anchors={self.num_anchors}, dims={(self.in_dim, *self.hidden, self.out_dim)}"
