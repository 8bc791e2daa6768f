"""The template: rest-pose mesh + skin weights (+ optional UVs and face mask).

Files: ``template/mesh.obj``, ``template/skin_weights.npz`` (``indices [V,K] int32``,
``weights [V,K] float32``, rows sum to 1), optional ``template/face_uv_mask.png``
(white = face region, in UV space, top row = v=1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsavatar.geometry.mesh_io import read_obj, write_obj
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_save_npz, read_mask, read_npz, write_image

SKIN_TOP_K = 4
"""Skinning slots per vertex K in ``skin_weights.npz`` as gsavatar's own templates write it (synthetic bodies,
imported SMPL-X bodies); readers accept any K."""


@dataclass
class Template:
    vertices: np.ndarray
    """Rest-pose vertex positions, metres.  # [V, 3] float32"""
    faces: np.ndarray
    """Triangle vertex indices.  # [F, 3] int64"""
    skin_indices: np.ndarray
    """Joint index per skinning slot.  # [V, K] int32"""
    skin_weights: np.ndarray
    """Skinning weight per slot, rows sum to 1.  # [V, K] float32"""
    uvs: np.ndarray | None = None
    """UV coordinates (OBJ convention, v up) or None.  # [T, 2] float32"""
    face_uvs: np.ndarray | None = None
    """UV index per triangle corner or None.  # [F, 3] int64"""
    face_uv_mask: np.ndarray | None = None
    """Face region in UV space (True = face), top row = v=1, or None.  # [H, W] bool"""

    @property
    def corner_uvs(self) -> np.ndarray | None:
        """UVs per triangle corner.  # [F, 3, 2] float32"""
        if self.uvs is None or self.face_uvs is None:
            return None
        return self.uvs[self.face_uvs]


def topk_skin_weights(w_dense: np.ndarray, k: int = SKIN_TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest skinning weights per vertex, renormalised to sum to 1; unused slots (a vertex with fewer
    than ``k`` non-zero weights) point at the vertex's main joint with weight 0.

    w_dense: [V, J] non-negative (negatives are clipped) -> (indices [V, k] int32, weights [V, k] float32).
    Raises RuntimeError when a vertex has no positive weight.
    """
    w_dense = np.clip(np.asarray(w_dense, dtype=np.float64), 0.0, None)
    k = min(k, w_dense.shape[1])
    idx = np.argsort(-w_dense, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(w_dense, idx, axis=1)
    s = w.sum(1, keepdims=True)
    if np.any(s <= 0):
        raise RuntimeError(f"{int(np.sum(s <= 0))} vertices have no skinning weight")
    w = w / s
    idx = np.where(w > 0, idx, idx[:, :1])  # unused slots point at the main joint (weight 0)
    return idx.astype(np.int32), w.astype(np.float32)


def validate_template(t: Template, num_joints: int, where: Path) -> None:
    """Check shapes, finiteness, index ranges and normalisation; raise SchemaError naming the file."""
    mesh = where / "mesh.obj"
    sw = where / "skin_weights.npz"
    V = t.vertices.shape[0]
    if t.vertices.ndim != 2 or t.vertices.shape[1] != 3:
        raise SchemaError(mesh, "v", f"vertices must be [V, 3], got {t.vertices.shape}")
    if t.faces.ndim != 2 or t.faces.shape[1] != 3:
        raise SchemaError(mesh, "f", f"faces must be triangles [F, 3], got {t.faces.shape}")
    e1 = t.vertices[t.faces[:, 1]] - t.vertices[t.faces[:, 0]]
    e2 = t.vertices[t.faces[:, 2]] - t.vertices[t.faces[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    if np.mean(area <= 1e-12) > 0.5:
        raise SchemaError(
            mesh, "f", f"{int(np.sum(area <= 1e-12))} of {len(area)} triangles are degenerate (zero area)"
        )
    if t.skin_indices.shape != t.skin_weights.shape or t.skin_indices.ndim != 2:
        raise SchemaError(
            sw, "indices/weights", f"must both be [V, K], got {t.skin_indices.shape} and {t.skin_weights.shape}"
        )
    if t.skin_indices.shape[0] != V:
        raise SchemaError(sw, "indices", f"has {t.skin_indices.shape[0]} rows but mesh.obj has {V} vertices")
    if not np.all(np.isfinite(t.skin_weights)):
        raise SchemaError(sw, "weights", "contains NaN/Inf")
    if t.skin_indices.min() < 0 or t.skin_indices.max() >= num_joints:
        raise SchemaError(sw, "indices", f"joint index out of range [0, {num_joints})")
    if t.skin_weights.min() < -1e-6:
        raise SchemaError(sw, "weights", "negative weights")
    s = t.skin_weights.sum(axis=1)
    bad = np.abs(s - 1.0) > 1e-3
    if bad.any():
        i = int(np.argmax(bad))
        raise SchemaError(sw, "weights", f"{int(bad.sum())} rows do not sum to 1 (vertex {i}: {s[i]:.4f})")


def load_template(where: str | Path, num_joints: int) -> Template:
    """Load and validate ``template/`` (mesh.obj, skin_weights.npz, optional face_uv_mask.png)."""
    where = Path(where)
    obj = read_obj(where / "mesh.obj")
    sw = where / "skin_weights.npz"
    z = read_npz(sw, keys=("indices", "weights"))
    if "indices" not in z or "weights" not in z:
        raise SchemaError(sw, "indices/weights", f"missing; has {sorted(z)}")
    for k, kinds in (("indices", "iu"), ("weights", "iuf")):
        if z[k].dtype.kind not in kinds:
            raise SchemaError(
                sw, k, f"expected {'integers' if kinds == 'iu' else 'real numbers'}, got dtype {z[k].dtype}"
            )
    idx = np.asarray(z["indices"], dtype=np.int32)
    w = np.asarray(z["weights"], dtype=np.float32)
    mask = None
    mpath = where / "face_uv_mask.png"
    if mpath.exists():
        mask = read_mask(mpath) > 0.5
    t = Template(obj.vertices, obj.faces, idx, w, obj.uvs, obj.face_uvs, mask)
    validate_template(t, num_joints, where)
    return t


def save_template(t: Template, where: str | Path) -> None:
    where = Path(where)
    write_obj(where / "mesh.obj", t.vertices, t.faces, t.uvs, t.face_uvs)
    atomic_save_npz(
        where / "skin_weights.npz", indices=t.skin_indices.astype(np.int32), weights=t.skin_weights.astype(np.float32)
    )
    if t.face_uv_mask is not None:
        write_image(where / "face_uv_mask.png", t.face_uv_mask.astype(np.float32))
