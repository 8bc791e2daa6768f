"""Small BVH files written by the tests: any joint names, rest positions and per-frame rotations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def write_bvh(
    path: Path,
    names: list[str],
    parents: list[int],
    rest: np.ndarray,
    angles_deg: np.ndarray,
    root_pos: np.ndarray,
    fps: float = 30.0,
    order: str = "ZXY",
) -> Path:
    """A BVH of ``names`` (parents first) with rest joint positions ``rest`` [J, 3] (file units), rotation
    channels ``order`` (intrinsic, e.g. ``ZXY`` = Zrotation Xrotation Yrotation) of angles ``angles_deg``
    [F, J, 3] (in ``order``), the root's position channels ``root_pos`` [F, 3]."""
    J = len(names)
    children = [[c for c in range(J) if parents[c] == j] for j in range(J)]
    lines = ["HIERARCHY"]
    rot_ch = " ".join(f"{a}rotation" for a in order)

    def block(j: int, depth: int) -> None:
        ind = "  " * depth
        off = rest[j] - (rest[parents[j]] if parents[j] >= 0 else 0.0)
        head = "ROOT" if parents[j] < 0 else "JOINT"
        lines.append(f"{ind}{head} {names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        chans = f"6 Xposition Yposition Zposition {rot_ch}" if parents[j] < 0 else f"3 {rot_ch}"
        lines.append(f"{ind}  CHANNELS {chans}")
        for c in children[j]:
            block(c, depth + 1)
        if not children[j]:
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 1 0", f"{ind}  }}"])
        lines.append(f"{ind}}}")

    for j in range(J):
        if parents[j] < 0:
            block(j, 0)
    F = angles_deg.shape[0]
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / fps:.8f}"]
    for f in range(F):
        row = []
        for j in range(J):
            if parents[j] < 0:
                row += list(root_pos[f])
            row += list(angles_deg[f, j])
        lines.append(" ".join(f"{v:.6f}" for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def random_angles(F: int, J: int, seed: int = 0, std_deg: float = 25.0) -> np.ndarray:
    """Per-frame, per-joint random rotation angles, degrees.  # [F, J, 3]"""
    return np.random.default_rng(seed).normal(0.0, std_deg, (F, J, 3))


def euler_matrix(order: str, angles_deg: np.ndarray) -> np.ndarray:
    """Intrinsic rotation of BVH channels ``order``. [..., 3] -> [..., 3, 3]"""
    return (
        Rotation.from_euler(order.upper(), angles_deg.reshape(-1, 3), degrees=True)
        .as_matrix()
        .reshape(*angles_deg.shape[:-1], 3, 3)
    )
