"""The ``localize`` stage's artifact: per-anchor pose-slot and face masks, and their file.

How the masks are built (skinning, ancestors, dilation, hands) is :mod:`gsavatar.prep.localize`.

File format (one ``.npz``, written atomically): ``pose [A, P] bool``, ``face [A] bool`` and ``header``:
a JSON string ``{"format": "gsavatar-localization", "version": 1, "num_anchors", "pose_dim",
"param_names", "settings"}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsavatar.data_schema.rig import Rig
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_save_npz, load_versioned_npz

MASKS_FORMAT = "gsavatar-localization"
MASKS_VERSION = 1


@dataclass
class LocalizationMasks:
    pose: np.ndarray
    """Per-anchor pose-slot mask.  # [A, P] bool"""
    face: np.ndarray
    """Per-anchor face-embedding mask.  # [A] bool"""
    param_names: list[str] = field(default_factory=list)
    """Rig parameter names (pose-vector order)."""
    settings: dict = field(default_factory=dict)
    """How the masks were built (ancestor_levels, dilation, adjacency, ...)."""

    def slot_of(self, rig: Rig, param: str) -> int:
        """First pose slot of parameter ``param``."""
        names = [p.name for p in rig.params]
        if param not in names:
            raise KeyError(f"unknown pose parameter {param!r}; e.g. {names[:5]}")
        return rig.slot_params().index(names.index(param))

    def save(self, path: str | Path) -> None:
        header = {
            "format": MASKS_FORMAT,
            "version": MASKS_VERSION,
            "num_anchors": int(self.pose.shape[0]),
            "pose_dim": int(self.pose.shape[1]),
            "param_names": list(self.param_names),
            "settings": self.settings,
        }
        atomic_save_npz(
            path, header=np.array(json.dumps(header)), pose=self.pose.astype(bool), face=self.face.astype(bool)
        )

    @classmethod
    def load(cls, path: str | Path) -> LocalizationMasks:
        path = Path(path)
        hdr, arrays = load_versioned_npz(
            path, MASKS_FORMAT, MASKS_VERSION, what="gsavatar localization", keys=("pose", "face")
        )
        for k in ("pose", "face"):
            if k not in arrays:
                raise SchemaError(path, k, "missing")
        pose, face = arrays["pose"].astype(bool), arrays["face"].astype(bool)
        if pose.shape != (hdr["num_anchors"], hdr["pose_dim"]) or face.shape != (hdr["num_anchors"],):
            raise SchemaError(path, "pose", f"shape {pose.shape} / face {face.shape} do not match the header")
        return cls(pose, face, list(hdr.get("param_names", [])), hdr.get("settings", {}))
