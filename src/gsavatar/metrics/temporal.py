"""How much an avatar changes with the frame, against the ground truth's change.

The frame-dependent half of the avatar (appearance latents, pose correctives) is what makes it
more than a static textured body. :func:`frame_dependence` compares the per-point colour spread
over frames of the avatar with that of the ground truth at the same surface points:

``std_pred = mean_{g,c} std_f pred[f, g, c]``, ``std_gt`` likewise, ``ratio = std_pred / std_gt``.

A static avatar has ratio 0; one that reproduces the ground truth's change has 1 (a larger
ratio means it changes more than the truth, e.g. noise).
"""

from __future__ import annotations

import torch
from torch import Tensor


def frame_dependence(pred: Tensor, gt: Tensor, weights: Tensor | None = None) -> dict[str, float]:
    """Colour spread over frames of a prediction vs the ground truth.

    Args:
        pred: Tensor  # [F, N, C] per-frame colour of N surface points (e.g. Gaussians' SH band 0), [0, 1]
        gt: Tensor  # [F, N, C] ground-truth colour at the same points and frames
        weights: Tensor | None  # [N] >= 0, e.g. 0 for points outside the region of interest; None = all 1

    Returns:
        {"std_pred", "std_gt", "ratio"} (ratio = std_pred / std_gt; NaN when std_gt is 0)
    """
    if pred.shape != gt.shape or pred.ndim != 3:
        raise ValueError(f"pred and gt must both be [F, N, C], got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if pred.shape[0] < 2:
        raise ValueError(f"need at least 2 frames, got {pred.shape[0]}")
    w = torch.ones(pred.shape[1], dtype=torch.float64) if weights is None else weights.detach().double().cpu()
    if w.shape != (pred.shape[1],) or not bool((w >= 0).all()) or float(w.sum()) <= 0:
        raise ValueError(f"weights must be [N] >= 0 with a positive sum, got shape {tuple(w.shape)}")

    def spread(x: Tensor) -> float:
        s = x.detach().double().cpu().std(0, correction=0).mean(-1)  # [N]
        return float((s * w).sum() / w.sum())

    sp, sg = spread(pred), spread(gt)
    return {"std_pred": sp, "std_gt": sg, "ratio": sp / sg if sg > 0 else float("nan")}
