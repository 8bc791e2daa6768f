"""Stage ``pose-template``: LBS of the template for every frame of ``motion.npz``."""

from __future__ import annotations

import numpy as np
import torch

from gsavatar.data_schema import Capture
from gsavatar.geometry.lbs import RigTensors, lbs, skinning_transforms


def pose_vertices(capture: Capture, frames: list[int], batch: int = 64) -> np.ndarray:
    """Posed template vertices for ``frames`` (world space, metres). -> [n, V, 3] float32."""
    m = capture.motion
    t = capture.template
    rt = RigTensors(capture.rig)
    verts = torch.from_numpy(t.vertices)
    idx = torch.from_numpy(t.skin_indices.astype(np.int64))
    w = torch.from_numpy(t.skin_weights)
    out = []
    with torch.no_grad():
        for s in range(0, len(frames), batch):
            f = frames[s : s + batch]
            T = skinning_transforms(
                rt,
                torch.from_numpy(m.pose[f]),
                torch.from_numpy(m.root_rotation[f]),
                torch.from_numpy(m.root_translation[f]),
            )
            out.append(lbs(verts, idx, w, T).numpy())
    v = np.concatenate(out, 0).astype(np.float32)
    bad = ~np.isfinite(v).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"motion.npz: posing frame {frames[int(np.argmax(bad))]} gives NaN/Inf vertices")
    return v
