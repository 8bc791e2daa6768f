"""Localized pose PCA with coefficient clamping (paper section 3.2, "Localized PCA").

A pose is transformed into PCA space, every coefficient is clamped to
``±clamp_sigma·σ`` (σ = the coefficient's standard deviation over the training
poses, sample estimate ``s / sqrt(F-1)``) and transformed back. The same transform is
applied at training and at test time.

``mode="local"`` runs an independent PCA per body-part group (``rig.slot_groups()``,
the seven :data:`~gsavatar.data_schema.rig.BODY_GROUPS`) with
``min(n_components, group dim, F-1, numerical rank)`` components each, so a group
never mixes with another. ``mode="global"`` runs one PCA over all ``P`` slots with
``min(n_components, P, F-1, rank)`` components.

Representation: all components are stacked into one matrix ``basis [P, C]`` whose
columns are unit vectors. In local mode each column is supported only on the slots
of its own group (exact zeros elsewhere), so ``project`` is one matmul pair and
other groups contribute exact zeros. Directions with (numerically) zero variance are
dropped, never kept with σ = 0 and an arbitrary direction: a group whose training
poses are constant projects onto its mean. Components are sign-normalised (largest
absolute entry positive) so fits are reproducible.

Note that with fewer components than dimensions, ``project`` is a low-rank
projection (the orthogonal complement of the kept components is replaced by the
mean), as in Animatable Gaussians / Spatial MLPs.

The fitted PCA is the artifact :class:`gsavatar.data_schema.pose_pca.PosePCA` (file format there).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from gsavatar.data_schema.pose_pca import PosePCA
from gsavatar.data_schema.rig import BODY_GROUPS, Rig


def _pca_block(X: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """PCA of centred data X [F, d]: (directions [d, r], sigma [r]) with r <= k non-degenerate."""
    F, d = X.shape
    if F < 2 or d == 0 or k <= 0:
        return np.zeros((d, 0)), np.zeros(0)
    _, s, vt = np.linalg.svd(X, full_matrices=False)
    # Numerical rank as in numpy.linalg.matrix_rank, plus an absolute floor for
    # all-constant data (s.max() == 0).
    tol = max(s.max(initial=0.0) * max(F, d) * np.finfo(np.float64).eps, 1e-12)
    r = min(k, int(np.sum(s > tol)))
    V = vt[:r].T.copy()  # [d, r]
    # Deterministic sign: largest-magnitude entry of each direction positive.
    idx = np.argmax(np.abs(V), axis=0)
    V *= np.where(V[idx, np.arange(r)] < 0, -1.0, 1.0)
    return V, s[:r] / np.sqrt(F - 1)


def fit_pose_pca(
    poses: np.ndarray,
    rig: Rig,
    n_components: int = 5,
    mode: Literal["local", "global"] = "local",
    clamp_sigma: float = 2.0,
) -> PosePCA:
    """Fit a (localized) pose PCA on training poses.

    poses: [F, P] radians, rig order. ``n_components``: per group (local) or in total
    (global); fewer are kept where a group has fewer dimensions, fewer than
    ``n_components + 1`` frames, or lower numerical rank.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != rig.pose_dim:
        raise ValueError(f"poses must be [F, {rig.pose_dim}], got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("poses contain NaN/Inf")
    if mode not in ("local", "global"):
        raise ValueError(f"mode must be 'local' or 'global', got {mode!r}")
    if n_components < 0:
        raise ValueError(f"n_components must be >= 0, got {n_components}")
    F, P = poses.shape
    mean = poses.mean(axis=0) if F else np.zeros(P)
    X = poses - mean
    slot_group = rig.slot_groups()
    blocks = (
        [(gi, np.flatnonzero(slot_group == gi)) for gi in range(len(BODY_GROUPS))]
        if mode == "local"
        else [(-1, np.arange(P))]
    )
    cols, sig, grp = [], [], []
    for gi, slots in blocks:
        V, s = _pca_block(X[:, slots], min(n_components, len(slots)))
        full = np.zeros((P, V.shape[1]))
        full[slots] = V
        cols.append(full)
        sig.append(s)
        grp.append(np.full(V.shape[1], gi, dtype=np.int64))
    return PosePCA(
        mode=mode,
        mean=mean,
        basis=np.concatenate(cols, axis=1) if cols else np.zeros((P, 0)),
        sigma=np.concatenate(sig),
        component_group=np.concatenate(grp),
        slot_group=slot_group.astype(np.int64),
        clamp_sigma=float(clamp_sigma),
        param_names=[p.name for p in rig.params],
        num_frames=F,
    )
