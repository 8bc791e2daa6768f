"""The ``sample-points`` stage's artifact: the anchor / control point / Gaussian hierarchy on the
template surface, and its file.

How the points are sampled and the interpolation tables built is :mod:`gsavatar.prep.sample_points`.

File format (one ``.npz``, written atomically): ``{level}.{field}`` arrays for the levels ``anchors``,
``control``, ``gaussians`` and the fields of :class:`PointSet` (``uv`` absent when the template has
none), the interpolation tables of :class:`Hierarchy`, and ``header``: a JSON string
``{"format": "gsavatar-hierarchy", "version": 1, "counts", "has_uv", "meta"}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_save_npz, load_versioned_npz

HIERARCHY_FORMAT = "gsavatar-hierarchy"
HIERARCHY_VERSION = 1
_POINT_FIELDS = ("position", "normal", "face_idx", "bary", "uv", "skin_indices", "skin_weights")
_LEVELS = ("anchors", "control", "gaussians")
_TABLES = (
    "gauss_anchor_idx",
    "gauss_anchor_w",
    "ctrl_anchor_idx",
    "ctrl_anchor_w",
    "gauss_ctrl_idx",
    "gauss_ctrl_w",
    "ctrl_neighbors",
)


@dataclass
class PointSet:
    """Points on the template surface with their transferred attributes."""

    position: np.ndarray
    """Rest-pose position, metres.  # [N, 3] float32"""
    normal: np.ndarray
    """Unit surface normal.  # [N, 3] float32"""
    face_idx: np.ndarray
    """Template triangle the point lies on.  # [N] int64"""
    bary: np.ndarray
    """Barycentric coordinates in that triangle (sum 1).  # [N, 3] float32"""
    uv: np.ndarray | None
    """UV (OBJ convention, v up) or None if the template has no UVs.  # [N, 2] float32"""
    skin_indices: np.ndarray
    """Joint index per skinning slot.  # [N, K] int32"""
    skin_weights: np.ndarray
    """Skinning weights, rows sum to 1.  # [N, K] float32"""

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def subset(self, idx: np.ndarray) -> PointSet:
        return PointSet(*(None if getattr(self, f) is None else getattr(self, f)[idx] for f in _POINT_FIELDS))


@dataclass
class Hierarchy:
    anchors: PointSet
    """Sparse anchors, one spatial MLP each (paper: 300)."""
    control: PointSet
    """Control points carrying positional offsets (paper: 10k)."""
    gaussians: PointSet
    """Gaussian centres (paper: 200k)."""
    gauss_anchor_idx: np.ndarray
    """3 nearest anchors of each Gaussian.  # [G, 3] int64"""
    gauss_anchor_w: np.ndarray
    """Inverse-distance weights (supp. eq. 1), rows sum to 1.  # [G, 3] float32"""
    ctrl_anchor_idx: np.ndarray
    """3 nearest anchors of each control point.  # [C, 3] int64"""
    ctrl_anchor_w: np.ndarray
    """Inverse-distance weights, rows sum to 1.  # [C, 3] float32"""
    gauss_ctrl_idx: np.ndarray
    """3 nearest control points of each Gaussian.  # [G, 3] int64"""
    gauss_ctrl_w: np.ndarray
    """Inverse-distance weights, rows sum to 1.  # [G, 3] float32"""
    ctrl_neighbors: np.ndarray
    """Nearest other control points (smoothness loss; paper: 5).  # [C, n] int64"""
    meta: dict = field(default_factory=dict)
    """Build settings (seed, counts, candidate sizes); saved."""
    timings: dict = field(default_factory=dict, compare=False)
    """Seconds per build stage (not saved, so files are byte-reproducible)."""

    @property
    def num_anchors(self) -> int:
        return len(self.anchors)

    @property
    def num_control(self) -> int:
        return len(self.control)

    @property
    def num_gaussians(self) -> int:
        return len(self.gaussians)

    # --- io ------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """One ``.npz`` (atomic): ``header`` JSON + ``{level}.{field}`` arrays + tables."""
        arrays: dict[str, np.ndarray] = {}
        for lvl in _LEVELS:
            ps: PointSet = getattr(self, lvl)
            for f in _POINT_FIELDS:
                v = getattr(ps, f)
                if v is not None:
                    arrays[f"{lvl}.{f}"] = v
        for t in _TABLES:
            arrays[t] = getattr(self, t)
        header = {
            "format": HIERARCHY_FORMAT,
            "version": HIERARCHY_VERSION,
            "counts": {lvl: len(getattr(self, lvl)) for lvl in _LEVELS},
            "has_uv": self.anchors.uv is not None,
            "meta": self.meta,
        }
        atomic_save_npz(path, header=np.array(json.dumps(header)), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Hierarchy:
        path = Path(path)
        hdr, arrays = load_versioned_npz(
            path,
            HIERARCHY_FORMAT,
            HIERARCHY_VERSION,
            what="gsavatar hierarchy",
            keys=(*(f"{lvl}.{f}" for lvl in _LEVELS for f in _POINT_FIELDS), *_TABLES),
        )
        levels = {}
        for lvl in _LEVELS:
            vals = []
            for f in _POINT_FIELDS:
                key = f"{lvl}.{f}"
                if key not in arrays and not (f == "uv" and not hdr.get("has_uv", True)):
                    raise SchemaError(path, key, "missing")
                vals.append(arrays.get(key))
            levels[lvl] = PointSet(*vals)
            if len(levels[lvl]) != hdr["counts"][lvl]:
                raise SchemaError(
                    path, f"{lvl}.position", f"has {len(levels[lvl])} rows, header says {hdr['counts'][lvl]}"
                )
        for t in _TABLES:
            if t not in arrays:
                raise SchemaError(path, t, "missing")
        return cls(**levels, **{t: arrays[t] for t in _TABLES}, meta=hdr.get("meta", {}))
