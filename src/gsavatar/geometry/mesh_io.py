"""Minimal, fast Wavefront OBJ reading/writing for triangle meshes with per-corner UVs.

UV convention (OBJ): ``u`` right, ``v`` UP, both in [0, 1]. Texture images are
stored top row first, so texel row ``y`` covers ``v = 1 - (y + 0.5) / H``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_write_text
from gsavatar.utils.paths import check_regular_file


class ObjMesh(NamedTuple):
    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int64, vertex indices
    uvs: np.ndarray | None  # [T, 2] float32, OBJ vt
    face_uvs: np.ndarray | None  # [F, 3] int64 indices into uvs


_MAX_INDEX = 1 << 40
"""Bound on |OBJ index| while parsing, so any index fits int64 (a real one is checked against the counts)."""
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _floats(path: Path, lineno: int, line: str, kind: str, n: int, what: str) -> list[float]:
    """The first ``n`` numbers after the keyword of an OBJ line; SchemaError naming the line unless
    there are ``n`` numbers, finite in float32 (what the mesh is stored as)."""
    parts = line.split()
    if len(parts) < n + 1:
        raise SchemaError(path, f"line {lineno}", f"{kind}: {what} needs {n} numbers, got {line.strip()!r}")
    try:
        vals = [float(t) for t in parts[1 : n + 1]]
    except ValueError:
        raise SchemaError(path, f"line {lineno}", f"{kind}: bad {what} {line.strip()!r}") from None
    if not all(math.isfinite(v) and abs(v) <= _FLOAT32_MAX for v in vals):
        raise SchemaError(path, f"line {lineno}", f"{kind}: non-finite {what} {line.strip()!r}")
    return vals


def read_obj(path: str | Path) -> ObjMesh:
    """Read a triangle OBJ; polygons are fan-triangulated.

    Raises SchemaError naming the file and the line for a malformed or non-finite ``v``/``vt``/``vn``
    line (``mesh.obj: line 1234: vt: non-finite texture coordinate 'vt nan 0.5'``) and for a face
    with a bad or out-of-range index; the file must be a regular file (a FIFO would block).
    """
    path = check_regular_file(path, "OBJ file")
    verts: list[list[float]] = []
    uvs: list[list[float]] = []
    faces: list[list[int]] = []
    fuvs: list[list[int]] = []
    face_lines: list[int] = []  # OBJ line of each triangle, for messages
    has_uv = True
    # errors=replace: binary junk then fails as a bad line or 'no faces' naming the file, not as a UnicodeDecodeError
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            if line.startswith("v "):
                verts.append(_floats(path, lineno, line, "v", 3, "vertex"))
            elif line.startswith("vt "):
                uvs.append(_floats(path, lineno, line, "vt", 2, "texture coordinate"))
            elif line.startswith("vn "):
                _floats(path, lineno, line, "vn", 3, "normal")  # unused, but a NaN there means a broken export
            elif line.startswith("f "):
                corners = line.split()[1:]
                if len(corners) < 3:
                    raise SchemaError(path, f"line {lineno}", "f: face needs at least 3 corners")
                vi, ti = [], []
                try:
                    for c in corners:
                        bits = c.split("/")
                        vi.append(int(bits[0]))
                        if len(bits) > 1 and bits[1]:
                            ti.append(int(bits[1]))
                except ValueError:
                    raise SchemaError(path, f"line {lineno}", f"f: bad face {line.strip()!r}") from None
                if any(i == 0 or abs(i) > _MAX_INDEX for i in vi + ti):
                    raise SchemaError(
                        path,
                        f"line {lineno}",
                        f"f: index out of range in {line.strip()!r} (OBJ indices start at 1, negatives count back)",
                    )
                if len(ti) != len(vi):
                    has_uv = False
                for k in range(1, len(vi) - 1):
                    faces.append([vi[0], vi[k], vi[k + 1]])
                    face_lines.append(lineno)
                    if len(ti) == len(vi):
                        fuvs.append([ti[0], ti[k], ti[k + 1]])
    if not verts or not faces:
        raise SchemaError(path, "", "no vertices or no faces")
    v = np.asarray(verts, dtype=np.float32)
    fa = _resolve(path, np.asarray(faces, dtype=np.int64), len(v), face_lines, "vertex")
    if has_uv and uvs and fuvs:
        t = np.asarray(uvs, dtype=np.float32)
        ft = _resolve(path, np.asarray(fuvs, dtype=np.int64), len(t), face_lines, "texture")
        return ObjMesh(v, fa, t, ft)
    return ObjMesh(v, fa, None, None)


def _resolve(path: Path, idx: np.ndarray, n: int, lines: list[int], what: str) -> np.ndarray:
    """1-based (negatives: relative) OBJ indices [F, 3] -> 0-based; SchemaError naming the first bad line."""
    out = np.where(idx < 0, idx + n, idx - 1)
    bad = ((out < 0) | (out >= n)).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise SchemaError(path, f"line {lines[i]}", f"f: {what} index out of range [1, {n}]")
    return out


def write_obj(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
) -> None:
    """Write a triangle OBJ atomically. vertices [V,3], faces [F,3] (0-based), uvs [T,2], face_uvs [F,3]."""
    lines = ["# gsavatar template"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    if uvs is not None and face_uvs is not None:
        lines += [f"vt {u:.6f} {w:.6f}" for u, w in np.asarray(uvs, dtype=np.float64)]
        f1, t1 = np.asarray(faces) + 1, np.asarray(face_uvs) + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f1, t1)]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(faces) + 1]
    atomic_write_text(path, "\n".join(lines) + "\n")
