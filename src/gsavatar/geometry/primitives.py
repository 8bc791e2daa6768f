"""Small test/benchmark meshes."""

from __future__ import annotations

import numpy as np


def icosphere(subdiv: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere by midpoint subdivision. -> vertices [V, 3] float32, faces [F, 3] int64 (outward CCW)."""
    t = (1 + 5**0.5) / 2
    V = [
        [-1, t, 0],
        [1, t, 0],
        [-1, -t, 0],
        [1, -t, 0],
        [0, -1, t],
        [0, 1, t],
        [0, -1, -t],
        [0, 1, -t],
        [t, 0, -1],
        [t, 0, 1],
        [-t, 0, -1],
        [-t, 0, 1],
    ]
    F = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
    verts = [np.array(v, float) / np.linalg.norm(v) for v in V]
    for _ in range(subdiv):
        cache: dict[tuple[int, int], int] = {}
        nf = []

        def mid(a: int, b: int) -> int:
            k = (min(a, b), max(a, b))
            if k not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[k] = len(verts) - 1
            return cache[k]

        for a, b, c in F:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        F = nf
    return np.array(verts, np.float32), np.array(F, np.int64)
