"""Minimal, fast Wavefront OBJ reading/writing for triangle meshes with per-corner UVs.

UV convention (OBJ): ``u`` right, ``v`` UP, both in [0, 1]. Texture images are
stored top row first, so texel row ``y`` covers ``v = 1 - (y + 0.5) / H``.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from gsavatar.data_schema.errors import SchemaError


class ObjMesh(NamedTuple):
    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int64, vertex indices
    uvs: np.ndarray | None  # [T, 2] float32, OBJ vt
    face_uvs: np.ndarray | None  # [F, 3] int64 indices into uvs


def read_obj(path: str | Path) -> ObjMesh:
    """Read a triangle OBJ; polygons are fan-triangulated. Raises SchemaError naming the line."""
    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "file not found")
    verts: list[list[float]] = []
    uvs: list[list[float]] = []
    faces: list[list[int]] = []
    fuvs: list[list[int]] = []
    has_uv = True
    # errors=replace: binary junk then fails as a bad line or 'no faces' naming the file, not as a UnicodeDecodeError
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            if line.startswith("v "):
                parts = line.split()
                if len(parts) < 4:
                    raise SchemaError(path, f"line {lineno}", "vertex needs 3 coordinates")
                try:
                    verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
                except ValueError:
                    raise SchemaError(path, f"line {lineno}", f"bad vertex {line.strip()!r}") from None
            elif line.startswith("vt "):
                parts = line.split()
                try:
                    uvs.append([float(parts[1]), float(parts[2])])
                except (ValueError, IndexError):
                    raise SchemaError(path, f"line {lineno}", f"bad texture coordinate {line.strip()!r}") from None
            elif line.startswith("f "):
                corners = line.split()[1:]
                if len(corners) < 3:
                    raise SchemaError(path, f"line {lineno}", "face needs at least 3 corners")
                vi, ti = [], []
                try:
                    for c in corners:
                        bits = c.split("/")
                        vi.append(int(bits[0]))
                        if len(bits) > 1 and bits[1]:
                            ti.append(int(bits[1]))
                except ValueError:
                    raise SchemaError(path, f"line {lineno}", f"bad face {line.strip()!r}") from None
                if len(ti) != len(vi):
                    has_uv = False
                for k in range(1, len(vi) - 1):
                    faces.append([vi[0], vi[k], vi[k + 1]])
                    if len(ti) == len(vi):
                        fuvs.append([ti[0], ti[k], ti[k + 1]])
    if not verts or not faces:
        raise SchemaError(path, "", "no vertices or no faces")
    v = np.asarray(verts, dtype=np.float32)
    fa = np.asarray(faces, dtype=np.int64)
    fa = np.where(fa < 0, fa + len(v), fa - 1)  # OBJ is 1-based, negatives are relative
    if fa.min() < 0 or fa.max() >= len(v):
        raise SchemaError(path, "f", f"face index out of range [1, {len(v)}]")
    if not np.all(np.isfinite(v)):
        raise SchemaError(path, "v", "vertex coordinates contain NaN/Inf")
    if has_uv and uvs and fuvs:
        t = np.asarray(uvs, dtype=np.float32)
        ft = np.asarray(fuvs, dtype=np.int64)
        ft = np.where(ft < 0, ft + len(t), ft - 1)
        if ft.min() < 0 or ft.max() >= len(t):
            raise SchemaError(path, "f", f"texture index out of range [1, {len(t)}]")
        return ObjMesh(v, fa, t, ft)
    return ObjMesh(v, fa, None, None)


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
              uvs: np.ndarray | None = None, face_uvs: np.ndarray | None = None) -> None:
    """Write a triangle OBJ atomically. vertices [V,3], faces [F,3] (0-based), uvs [T,2], face_uvs [F,3]."""
    from gsavatar.utils.io import atomic_write_text

    lines = ["# gsavatar template"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    if uvs is not None and face_uvs is not None:
        lines += [f"vt {u:.6f} {w:.6f}" for u, w in np.asarray(uvs, dtype=np.float64)]
        f1, t1 = np.asarray(faces) + 1, np.asarray(face_uvs) + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f1, t1)]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(faces) + 1]
    atomic_write_text(path, "\n".join(lines) + "\n")
