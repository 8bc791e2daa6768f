"""Standard 3DGS ``.ply`` export of posed Gaussians (the INRIA 3DGS layout).

Binary little-endian, one ``vertex`` element with float32 properties, in order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

- ``opacity`` is the logit of the activated opacity, ``scale_*`` the log of the
  activated scales (metres), ``rot_*`` the unit quaternion wxyz.
- ``f_rest`` is channel-major as in the INRIA code: ``f_rest_{c*(K-1)+k}`` is SH
  coefficient ``k+1`` of colour channel ``c`` (``features_rest.transpose(1, 2)``).
- Normals are zero (viewers ignore them).

This is what common splat viewers (SuperSplat, the INRIA SIBR viewer, antimatter15)
open. :func:`read_ply` reads it back (activated values), for tests and tools.

Up axis: our world is the capture's, **Y up** (:data:`WORLD_UP`; the synthetic captures, the imported
bodies and the orbit cameras all share it). 3DGS viewers expect the COLMAP convention, Y down (``-y`` up);
Blender-like tools Z up. ``up_axis`` (:data:`UP_AXES`) rotates the Gaussians rigidly before writing so the
given axis points where our +Y did: positions, rotations (``q_R * q``) and the SH coefficients of every band
(:func:`sh_rotation`), so the colour seen from a rotated camera is unchanged. (Before 2026-12-05 the table
assumed a Z-up world: ``-y`` and ``y`` laid the body on its back, and ``z``, the default, was ours unchanged;
the default is now ``y``, the same bytes.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from gsavatar.render.sh import sh_bases
from gsavatar.utils.io import atomic_path
from gsavatar.utils.outdir import PLY_COMMENT

UpAxis = Literal["y", "-y", "z"]
WORLD_UP = np.array([0.0, 1.0, 0.0])
"""Our world's up direction (the capture's: cameras' image-down is -Y, the body stands along +Y)."""
UP_AXES: dict[str, np.ndarray] = {
    "y": np.eye(3),  # ours (the capture's world): unchanged
    "-y": np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]]),  # 180 deg about x: +y -> -y (COLMAP / 3DGS, Y down)
    "z": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # +90 deg about x: +y -> +z (Z-up tools)
}
"""Up axis of the written file -> rotation [3, 3] applied to our Y-up world (``R @ WORLD_UP`` = that axis)."""

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


class PlyGaussians(NamedTuple):
    means: np.ndarray
    """Centres, metres.  # [N, 3] float32"""
    quats: np.ndarray
    """Unit rotations wxyz.  # [N, 4] float32"""
    scales: np.ndarray
    """Activated scales, metres.  # [N, 3] float32"""
    opacities: np.ndarray
    """Activated opacities.  # [N] float32"""
    sh: np.ndarray
    """SH coefficients, [:, 0] = DC.  # [N, K, 3] float32"""
    property_names: list[str]
    """Vertex property names in file order."""


def ply_property_names(num_sh: int) -> list[str]:
    """Property names of the standard layout for ``num_sh = (degree+1)^2`` coefficients."""
    rest = [f"f_rest_{i}" for i in range(3 * (num_sh - 1))]
    return [
        "x",
        "y",
        "z",
        "nx",
        "ny",
        "nz",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        *rest,
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """Rotation [3, 3] taking our Y-up world to one whose up is ``up_axis`` (see :data:`UP_AXES`)."""
    if up_axis not in UP_AXES:
        raise ValueError(f"up_axis must be one of {'/'.join(UP_AXES)}, got {up_axis!r}")
    return UP_AXES[up_axis].copy()


def sh_rotation(R: np.ndarray, num_sh: int) -> np.ndarray:
    """Matrix D [K, K] with ``sh' = D @ sh`` (per colour channel) for Gaussians rotated by ``R`` [3, 3]:
    ``sum_k Y_k(d) sh'_k = sum_k Y_k(R^T d) sh_k`` for every direction d (block diagonal per band; fitted
    on 64 directions, exact up to rounding since each band is closed under rotation)."""
    deg = round(np.sqrt(num_sh)) - 1
    if (deg + 1) ** 2 != num_sh or not 0 <= deg <= 3:
        raise ValueError(f"num_sh must be (d+1)^2 with d in [0, 3], got {num_sh}")
    g = np.random.default_rng(0).normal(size=(64, 3))
    d = torch.as_tensor(g / np.linalg.norm(g, axis=1, keepdims=True))
    Rt = torch.as_tensor(np.asarray(R, np.float64))
    b_new = sh_bases(deg, d).numpy()  # [M, K]
    b_old = sh_bases(deg, d @ Rt).numpy()  # rows: Y(R^T d)
    D = np.linalg.lstsq(b_new, b_old, rcond=None)[0]
    D[np.abs(D) < 1e-12] = 0.0
    return D


def rotate_gaussians(
    R: np.ndarray, means: np.ndarray, quats: np.ndarray, sh: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate Gaussians rigidly about the origin by ``R`` [3, 3].

    means [N, 3], quats [N, 4] wxyz, sh [N, K, 3] -> (R means, q_R * q, D sh) as float64
    """
    from scipy.spatial.transform import Rotation

    m, q, c = (np.asarray(a, np.float64) for a in (means, quats, sh))
    rw = Rotation.from_matrix(R).as_quat()  # xyzw
    w0, v0 = rw[3], rw[:3]
    w1, v1 = q[:, :1], q[:, 1:]
    qn = np.concatenate([w0 * w1 - v1 @ v0[:, None], w0 * v1 + w1 * v0[None] + np.cross(v0[None], v1)], axis=1)
    D = sh_rotation(R, c.shape[1])
    return m @ np.asarray(R, np.float64).T, qn, np.einsum("kj,njc->nkc", D, c)


def _np(x: Tensor | np.ndarray) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, Tensor) else np.asarray(x, np.float64)


def write_ply(
    path: str | Path,
    means: Tensor | np.ndarray,
    quats: Tensor | np.ndarray,
    scales: Tensor | np.ndarray,
    opacities: Tensor | np.ndarray,
    sh: Tensor | np.ndarray,
    up_axis: UpAxis = "y",
) -> None:
    """Write one set of Gaussians (atomic).

    Args:
        means: [N, 3] world centres, metres
        quats: [N, 4] wxyz (normalised here)
        scales: [N, 3] activated scales > 0, metres
        opacities: [N] activated opacities in (0, 1)
        sh: [N, K, 3] SH coefficients (K = (degree+1)^2), [:, 0] = DC
        up_axis: up axis of the file (``y``: ours, unchanged; ``-y``: 3DGS / COLMAP viewers; ``z``: Z-up tools),
            :data:`UP_AXES`
    """
    R = up_axis_rotation(up_axis)
    m, q, s, o, c = map(_np, (means, quats, scales, opacities, sh))
    N = m.shape[0]
    for name, a, shape in (("means", m, (N, 3)), ("quats", q, (N, 4)), ("scales", s, (N, 3)), ("opacities", o, (N,))):
        if a.shape != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {list(a.shape)}")
    if c.ndim != 3 or c.shape[0] != N or c.shape[2] != 3 or round(np.sqrt(c.shape[1])) ** 2 != c.shape[1]:
        raise ValueError(f"sh must be [{N}, (d+1)^2, 3], got {list(c.shape)}")
    K = c.shape[1]
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    if up_axis != "y":
        m, q, c = rotate_gaussians(R, m, q, c)
    o = np.clip(o, 1e-7, 1 - 1e-7)
    cols = [
        m,
        np.zeros((N, 3)),
        c[:, 0, :],
        c[:, 1:, :].transpose(0, 2, 1).reshape(N, 3 * (K - 1)),  # channel-major
        np.log(o / (1 - o))[:, None],
        np.log(np.maximum(s, 1e-30)),
        q,
    ]
    data = np.concatenate(cols, axis=1).astype("<f4")
    names = ply_property_names(K)
    header = "ply\nformat binary_little_endian 1.0\n" + PLY_COMMENT + "\n" + f"element vertex {N}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())


def export_frame_ply(path: str | Path, out, frame: int = 0, up_axis: UpAxis = "y") -> None:
    """Write frame ``frame`` of an :class:`~gsavatar.models.avatar.AvatarOutput` (posed)."""
    write_ply(
        path,
        out.means[frame],
        out.quats[frame],
        out.scales[frame],
        out.opacities[frame],
        out.sh[frame],
        up_axis=up_axis,
    )


def read_ply(path: str | Path) -> PlyGaussians:
    """Read a binary little-endian 3DGS ``.ply`` back into activated values."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    lines = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary_little_endian PLY is supported")
    n, props, in_vertex, n_elements = 0, [], False, 0
    for ln in lines:
        tok = ln.split()
        if tok[:1] == ["element"]:
            n_elements += 1
            in_vertex = tok[1] == "vertex"
            if in_vertex and n_elements != 1:
                raise ValueError(f"{path}: 'vertex' must be the first element")
            if in_vertex:
                n = int(tok[2])
        elif tok[:1] == ["property"] and in_vertex:
            if tok[1] == "list":
                raise ValueError(f"{path}: list properties in 'vertex' are not supported")
            props.append((tok[2], "<" + _PLY_TYPES[tok[1]]))
    arr = np.frombuffer(raw, dtype=np.dtype(props), count=n, offset=end + len(b"end_header\n"))
    names = [p for p, _ in props]
    col = lambda *ks: np.stack([arr[k].astype(np.float64) for k in ks], axis=1)  # noqa: E731
    n_rest = sum(k.startswith("f_rest_") for k in names)
    K = 1 + n_rest // 3
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
    rest = (
        col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, K - 1).transpose(0, 2, 1)
        if n_rest
        else np.zeros((n, 0, 3))
    )
    q = col("rot_0", "rot_1", "rot_2", "rot_3")
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    return PlyGaussians(
        means=col("x", "y", "z").astype(np.float32),
        quats=q.astype(np.float32),
        scales=np.exp(col("scale_0", "scale_1", "scale_2")).astype(np.float32),
        opacities=(1.0 / (1.0 + np.exp(-arr["opacity"].astype(np.float64)))).astype(np.float32),
        sh=np.concatenate([dc, rest], axis=1).astype(np.float32),
        property_names=names,
    )


def ply_to_torch(g: PlyGaussians, device: torch.device | str = "cpu") -> dict[str, Tensor]:
    """Tensors ready for ``render.rasterize`` (means, quats, scales, opacities, colors=sh)."""
    t = lambda a: torch.as_tensor(a, device=device)  # noqa: E731
    return {
        "means": t(g.means),
        "quats": t(g.quats),
        "scales": t(g.scales),
        "opacities": t(g.opacities),
        "colors": t(g.sh),
    }
