"""The ``fit-pca`` stage's artifact: a (localized) pose PCA with coefficient clamping, and its file.

Fitting lives in :mod:`gsavatar.prep.pca` (the method is described there); this module holds the
type every consumer reads (the model applies :meth:`PosePCA.project` at training and test time).

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

from gsavatar.data_schema.rig import BODY_GROUPS, Rig
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_save_npz, load_versioned_npz

PCA_FORMAT = "gsavatar-pose-pca"
PCA_VERSION = 1


def clamp_coefficients(coeffs, limit):
    """PCA coefficients clamped to ``±limit`` (the box of section 3.2), the one clamp of every PCA we use
    (pose PCA of the avatar and the predictor, the predictor's latent PCA).

    coeffs [..., C], limit [..., C] broadcastable, >= 0; numpy arrays or torch tensors (differentiable,
    zero gradient through clamped coefficients) -> [..., C] of the same type
    """
    if isinstance(coeffs, np.ndarray):
        return np.maximum(np.minimum(coeffs, limit), -limit)
    return coeffs.minimum(limit).maximum(-limit)


def pca_project(x, mean, basis, limit):
    """Into PCA space, clamp every coefficient (:func:`clamp_coefficients`), back.

    x [..., P], mean [P], basis [P, C] unit columns, limit [C] (``clamp_sigma * sigma``) -> [..., P];
    numpy arrays or torch tensors (all of one kind, one dtype)
    """
    return clamp_coefficients((x - mean) @ basis, limit) @ basis.T + mean


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
        return clamp_coefficients(coeffs, self._arrays(coeffs)[2])

    def project(self, poses):
        """Transform to PCA space, clamp each coefficient to ±clamp_sigma·σ, transform back.

        poses: [B, P] numpy or torch (differentiable; gradient is zero through clamped
        coefficients) -> [B, P] of the same type, dtype and device.
        """
        if not isinstance(poses, np.ndarray):
            import torch

            if not isinstance(poses, torch.Tensor):
                poses = np.asarray(poses, dtype=np.float64)
        self._check(poses)
        return pca_project(poses, *self._arrays(poses))

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
        path = Path(path)
        hdr, arrays = load_versioned_npz(
            path,
            PCA_FORMAT,
            PCA_VERSION,
            what="gsavatar pose PCA",
            keys=("mean", "basis", "sigma", "component_group", "slot_group"),
        )
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
