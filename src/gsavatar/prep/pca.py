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

File format (one ``.npz``, written atomically): arrays ``mean [P] f8``,
``basis [P, C] f8``, ``sigma [C] f8``, ``component_group [C] i8``,
``slot_group [P] i8`` and ``header``: a JSON string
``{"format": "gsavatar-pose-pca", "version": 1, "mode", "clamp_sigma",
"n_components", "groups", "components_per_group", "param_names", "pose_dim",
"num_frames"}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from gsavatar.data_schema.errors import SchemaError
from gsavatar.data_schema.rig import BODY_GROUPS, Rig

PCA_FORMAT = "gsavatar-pose-pca"
PCA_VERSION = 1


@dataclass
class PosePCA:
    mode: Literal["local", "global"]
    """``local``: one PCA per body-part group; ``global``: one PCA over the whole pose."""
    mean: np.ndarray
    """Training mean pose.  # [P] float64"""
    basis: np.ndarray
    """Unit principal directions as columns (local: block-sparse per group).  # [P, C] float64"""
    sigma: np.ndarray
    """Standard deviation of each coefficient over the training poses (> 0).  # [C] float64"""
    component_group: np.ndarray
    """Group of each component: index into :data:`BODY_GROUPS` (local) or -1 (global).  # [C] int64"""
    slot_group: np.ndarray
    """Group index of every pose slot (``rig.slot_groups()``).  # [P] int64"""
    clamp_sigma: float = 2.0
    """Coefficients are clamped to ``±clamp_sigma·sigma``."""
    param_names: list[str] = field(default_factory=list)
    """Rig parameter names (pose-vector order), to check a rig against the fit."""
    num_frames: int = 0
    """Number of training poses the PCA was fit on."""
    _torch_cache: dict = field(default_factory=dict, repr=False, compare=False)

    # --- derived -------------------------------------------------------------
    @property
    def pose_dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def num_components(self) -> int:
        return int(self.basis.shape[1])

    def components_per_group(self) -> dict[str, int]:
        """Number of kept components per body-part group (local) or ``{"global": C}``."""
        if self.mode == "global":
            return {"global": self.num_components}
        return {g: int(np.sum(self.component_group == gi)) for gi, g in enumerate(BODY_GROUPS)}

    def check_rig(self, rig: Rig) -> None:
        """Raise ``ValueError`` if ``rig`` is not the rig this PCA was fit for."""
        names = [p.name for p in rig.params]
        if rig.pose_dim != self.pose_dim or (self.param_names and names != self.param_names):
            raise ValueError(
                f"pose PCA was fit for {self.pose_dim} slots / params {self.param_names[:3]}..., "
                f"rig has {rig.pose_dim} slots / params {names[:3]}..."
            )

    # --- transforms ----------------------------------------------------------
    def _arrays(self, like):
        """(mean, basis, limit) in the array type/dtype/device of ``like``."""
        if isinstance(like, np.ndarray):
            dt = like.dtype if np.issubdtype(like.dtype, np.floating) else np.float64
            return self.mean.astype(dt), self.basis.astype(dt), (self.clamp_sigma * self.sigma).astype(dt)
        import torch

        key = (like.device, like.dtype)
        if key not in self._torch_cache:
            self._torch_cache[key] = tuple(
                torch.as_tensor(a, dtype=like.dtype, device=like.device)
                for a in (self.mean, self.basis, self.clamp_sigma * self.sigma)
            )
        return self._torch_cache[key]

    def _check(self, poses) -> None:
        if poses.ndim != 2 or poses.shape[1] != self.pose_dim:
            raise ValueError(f"poses must be [B, {self.pose_dim}], got {tuple(poses.shape)}")

    def transform(self, poses):
        """Pose -> PCA coefficients (no clamping). [B, P] np/torch -> [B, C]"""
        self._check(poses)
        mean, basis, _ = self._arrays(poses)
        return (poses - mean) @ basis

    def inverse(self, coeffs):
        """PCA coefficients -> pose. [B, C] np/torch -> [B, P]"""
        mean, basis, _ = self._arrays(coeffs)
        return coeffs @ basis.T + mean

    def clamp(self, coeffs):
        """Clamp coefficients to ``±clamp_sigma·sigma``. [B, C] -> [B, C]"""
        _, _, lim = self._arrays(coeffs)
        if isinstance(coeffs, np.ndarray):
            return np.clip(coeffs, -lim, lim)
        import torch

        return torch.clamp(coeffs, -lim, lim)

    def project(self, poses):
        """Transform to PCA space, clamp each coefficient to ±clamp_sigma·σ, transform back.

        poses: [B, P] numpy or torch (differentiable; gradient is zero through clamped
        coefficients) -> [B, P] of the same type, dtype and device.
        """
        if not isinstance(poses, np.ndarray):
            import torch

            if not isinstance(poses, torch.Tensor):
                poses = np.asarray(poses, dtype=np.float64)
        return self.inverse(self.clamp(self.transform(poses)))

    # --- io ------------------------------------------------------------------
    def header(self) -> dict:
        return {
            "format": PCA_FORMAT,
            "version": PCA_VERSION,
            "mode": self.mode,
            "clamp_sigma": float(self.clamp_sigma),
            "n_components": self.num_components,
            "groups": list(BODY_GROUPS) if self.mode == "local" else ["global"],
            "components_per_group": self.components_per_group(),
            "param_names": list(self.param_names),
            "pose_dim": self.pose_dim,
            "num_frames": int(self.num_frames),
        }

    def save(self, path: str | Path) -> None:
        from gsavatar.utils.io import atomic_save_npz

        atomic_save_npz(
            path,
            header=np.array(json.dumps(self.header())),
            mean=self.mean.astype(np.float64),
            basis=self.basis.astype(np.float64),
            sigma=self.sigma.astype(np.float64),
            component_group=self.component_group.astype(np.int64),
            slot_group=self.slot_group.astype(np.int64),
        )

    @classmethod
    def load(cls, path: str | Path) -> PosePCA:
        from gsavatar.utils.io import load_versioned_npz

        path = Path(path)
        hdr, arrays = load_versioned_npz(path, PCA_FORMAT, PCA_VERSION, what="gsavatar pose PCA",
                                         keys=("mean", "basis", "sigma", "component_group", "slot_group"))
        for key in ("mean", "basis", "sigma", "component_group", "slot_group"):
            if key not in arrays:
                raise SchemaError(path, key, "missing")
        if hdr.get("mode") not in ("local", "global"):
            raise SchemaError(path, "header.mode", f"expected 'local' or 'global', got {hdr.get('mode')!r}")
        P, C = arrays["basis"].shape if arrays["basis"].ndim == 2 else (-1, -1)
        if arrays["mean"].shape != (P,) or arrays["sigma"].shape != (C,) or arrays["component_group"].shape != (C,):
            raise SchemaError(path, "basis", "inconsistent shapes of mean/basis/sigma/component_group")
        return cls(
            mode=hdr["mode"],
            mean=arrays["mean"].astype(np.float64),
            basis=arrays["basis"].astype(np.float64),
            sigma=arrays["sigma"].astype(np.float64),
            component_group=arrays["component_group"].astype(np.int64),
            slot_group=arrays["slot_group"].astype(np.int64),
            clamp_sigma=float(hdr["clamp_sigma"]),
            param_names=list(hdr.get("param_names", [])),
            num_frames=int(hdr.get("num_frames", 0)),
        )


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
    blocks = [(gi, np.flatnonzero(slot_group == gi)) for gi in range(len(BODY_GROUPS))] if mode == "local" else [(-1, np.arange(P))]
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
