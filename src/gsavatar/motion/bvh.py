"""A small, strict BVH (Biovision Hierarchy) motion reader and its forward kinematics.

Format (what is accepted)::

    HIERARCHY
    ROOT Hips
    {
        OFFSET 0 0 0
        CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
        JOINT LeftUpLeg
        {
            OFFSET 1.36 -1.79 0.84
            CHANNELS 3 Zrotation Yrotation Xrotation
            End Site
            {
                OFFSET 0 -1 0
            }
        }
    }
    MOTION
    Frames: 2
    Frame Time: 0.0083333
    <one line per frame, one number per channel, in hierarchy order>

- Any joint may have any subset of the six channels in any order (position channels
  included, not only on the root); a joint may have zero channels.
- Rows beyond the declared ``Frames:`` count are ignored with a warning (some exporters
  are off by one); fewer rows than declared is an error.
- Several ``ROOT`` blocks are allowed (each starts a new tree, parent -1).
- Angles are degrees. Each joint's local transform is
  ``T(offset + (Xposition, Yposition, Zposition)) @ R_c1 @ R_c2 @ R_c3`` with the
  rotation channels multiplied in the order they are listed (intrinsic rotations), the
  standard BVH convention (a ``Zrotation Yrotation Xrotation`` joint has ``R = Rz Ry Rx``).

Malformed files raise :class:`~gsavatar.utils.errors.SchemaError` naming the
file and the line: truncated MOTION sections, rows with the wrong number of values,
non-numeric or NaN/Inf values, bad channel names/counts, unbalanced braces, no frames
(``Frames: 0``), a ``Frame Time`` outside [1/MAX_FPS, 1/MIN_FPS] s (the plausible frame rates of
:mod:`gsavatar.data_schema.limits`: 1e9 s per frame made resampling ask for TiB), joints nested
deeper than MAX_DEPTH, files over MAX_BVH_BYTES or that are not regular files (a FIFO would block).
Nothing is allocated from a declared count before the rows that back it are found.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsavatar.data_schema.limits import MAX_FPS, MIN_FPS
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.paths import check_regular_file

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
_ALL_CHANNELS = POSITION_CHANNELS + ROTATION_CHANNELS
MAX_DEPTH = 256
"""Deepest joint nesting accepted (human skeletons: < 30; the parser recurses once per level)."""
MAX_BVH_BYTES = 1 << 30
"""Largest BVH file read (1 GiB; CMU clips are < 10 MB, hours of 120 Hz mocap a few hundred MB)."""


@dataclass
class BvhMotion:
    """A parsed BVH file (skeleton + raw channel values)."""

    names: list[str]
    """Joint names in file (hierarchy, parents-first) order."""
    parents: np.ndarray
    """Parent index per joint, -1 for a root.  # [J] int64"""
    offsets: np.ndarray
    """Rest offset of each joint from its parent (root: from the origin), file units.  # [J, 3] float64"""
    channels: list[list[str]]
    """Channel names per joint, in file order (e.g. ``['Zrotation', 'Yrotation', 'Xrotation']``)."""
    motion: np.ndarray
    """Channel values per frame; columns follow the joints' channels in hierarchy order.  # [F, C] float64"""
    frame_time: float
    """Seconds per frame."""
    end_sites: list[tuple[int, np.ndarray]] = field(default_factory=list)
    """``(joint index, offset [3])`` for every ``End Site`` block."""
    path: str = ""
    """Source file (for messages)."""

    # --- derived views -----------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def num_channels(self) -> int:
        return int(self.motion.shape[1])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def channel_start(self) -> np.ndarray:
        """First motion column of each joint.  # [J] int64"""
        sizes = np.array([len(c) for c in self.channels], dtype=np.int64)
        return np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)

    def joint_index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"{self.path or 'BVH'}: no joint {name!r}; joints are {self.names}") from None

    def children(self) -> list[list[int]]:
        out: list[list[int]] = [[] for _ in self.names]
        for j, p in enumerate(self.parents.tolist()):
            if p >= 0:
                out[p].append(j)
        return out


# --------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------
class _Tokens:
    """Whitespace tokens with their 1-based line numbers."""

    def __init__(self, lines: list[str], path: Path, stop_line: int) -> None:
        self.toks: list[tuple[str, int]] = []
        for ln in range(stop_line):
            for t in lines[ln].split():
                self.toks.append((t, ln + 1))
        self.i = 0
        self.path = path
        self.last_line = stop_line

    def peek(self) -> str | None:
        return self.toks[self.i][0] if self.i < len(self.toks) else None

    def line(self) -> int:
        return self.toks[self.i][1] if self.i < len(self.toks) else self.last_line

    def next(self, what: str) -> str:
        if self.i >= len(self.toks):
            raise SchemaError(self.path, f"line {self.last_line}", f"unexpected end of HIERARCHY, expected {what}")
        t = self.toks[self.i][0]
        self.i += 1
        return t

    def expect(self, word: str) -> None:
        ln = self.line()
        t = self.next(repr(word))
        if t != word:
            raise SchemaError(self.path, f"line {ln}", f"expected {word!r}, got {t!r}")

    def number(self, what: str) -> float:
        ln = self.line()
        t = self.next(what)
        try:
            v = float(t)
        except ValueError:
            raise SchemaError(self.path, f"line {ln}", f"{what}: expected a number, got {t!r}") from None
        if not np.isfinite(v):
            raise SchemaError(self.path, f"line {ln}", f"{what}: not finite ({t})")
        return v


def _parse_joint(tk: _Tokens, name: str, parent: int, out: dict, depth: int = 0) -> None:
    """Parse ``{ OFFSET .. CHANNELS .. (JOINT|End Site)* }`` of one joint (name already read)."""
    if depth > MAX_DEPTH:
        raise SchemaError(tk.path, f"line {tk.line()}", f"JOINT {name!r}: joints nested deeper than {MAX_DEPTH} levels")
    idx = len(out["names"])
    if name in out["names"]:
        raise SchemaError(tk.path, f"line {tk.line()}", f"duplicate joint name {name!r}")
    out["names"].append(name)
    out["parents"].append(parent)
    out["offsets"].append([0.0, 0.0, 0.0])
    out["channels"].append([])
    tk.expect("{")
    seen_offset = False
    while True:
        ln = tk.line()
        t = tk.next("'}' closing joint " + repr(name))
        if t == "}":
            break
        if t == "OFFSET":
            out["offsets"][idx] = [tk.number(f"{name}.OFFSET[{k}]") for k in range(3)]
            seen_offset = True
        elif t == "CHANNELS":
            cl = tk.line()
            ct = tk.next("channel count")
            try:
                n = int(ct)
            except ValueError:
                raise SchemaError(
                    tk.path, f"line {cl}", f"{name}.CHANNELS: expected a channel count, got {ct!r}"
                ) from None
            if not 0 <= n <= 6:
                raise SchemaError(tk.path, f"line {cl}", f"{name}.CHANNELS: count must be 0..6, got {n}")
            chans = []
            for k in range(n):
                kl = tk.line()
                c = tk.next(f"channel {k + 1} of {n} for {name}")
                if c not in _ALL_CHANNELS:
                    raise SchemaError(
                        tk.path,
                        f"line {kl}",
                        f"{name}.CHANNELS: unknown channel {c!r} (declared {n} channels; valid: {list(_ALL_CHANNELS)})",
                    )
                if c in chans:
                    raise SchemaError(tk.path, f"line {kl}", f"{name}.CHANNELS: channel {c!r} listed twice")
                chans.append(c)
            out["channels"][idx] = chans
        elif t == "JOINT":
            child = tk.next("joint name")
            _parse_joint(tk, child, idx, out, depth + 1)
        elif t == "End":
            tk.expect("Site")
            tk.expect("{")
            tk.expect("OFFSET")
            off = np.array([tk.number(f"{name}.End Site.OFFSET[{k}]") for k in range(3)])
            tk.expect("}")
            out["end_sites"].append((idx, off))
        else:
            raise SchemaError(
                tk.path,
                f"line {ln}",
                f"unexpected {t!r} in joint {name!r} (expected OFFSET, CHANNELS, JOINT, End Site or '}}')",
            )
    if not seen_offset:
        raise SchemaError(tk.path, f"line {tk.line()}", f"joint {name!r} has no OFFSET")


def read_bvh(path: str | Path) -> BvhMotion:
    """Parse a BVH file. Raises :class:`SchemaError` (file, ``line N``) on malformed input."""
    path = check_regular_file(path, "BVH file", MAX_BVH_BYTES)
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = text.splitlines()
    motion_line = next((i for i, l in enumerate(lines) if l.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise SchemaError(path, "MOTION", "no MOTION section (file truncated?)")
    tk = _Tokens(lines, path, motion_line)
    if tk.peek() != "HIERARCHY":
        raise SchemaError(path, f"line {tk.line()}", f"file must start with HIERARCHY, got {tk.peek()!r}")
    tk.next("HIERARCHY")
    out: dict = {"names": [], "parents": [], "offsets": [], "channels": [], "end_sites": []}
    while tk.peek() is not None:
        ln = tk.line()
        t = tk.next("ROOT")
        if t != "ROOT":
            raise SchemaError(path, f"line {ln}", f"expected ROOT, got {t!r} (unbalanced braces?)")
        _parse_joint(tk, tk.next("root name"), -1, out)
    if not out["names"]:
        raise SchemaError(path, "HIERARCHY", "no joints")
    C = sum(len(c) for c in out["channels"])

    # --- MOTION header -------------------------------------------------------------
    def header(i: int, key: str) -> str:
        if i >= len(lines):
            raise SchemaError(path, f"line {i + 1}", f"MOTION section truncated: missing '{key}'")
        s = lines[i].strip()
        if not s.lower().startswith(key.lower()):
            raise SchemaError(path, f"line {i + 1}", f"expected '{key} ...', got {s[:40]!r}")
        return s[len(key) :].strip()

    i = motion_line + 1
    while i < len(lines) and not lines[i].strip():
        i += 1
    fs = header(i, "Frames:")
    try:
        F = int(fs)
    except ValueError:
        raise SchemaError(path, f"line {i + 1}", f"Frames: expected an integer, got {fs!r}") from None
    if F < 0:
        raise SchemaError(path, f"line {i + 1}", f"Frames: must be >= 1, got {F}")
    if F == 0:
        raise SchemaError(path, f"line {i + 1}", "Frames: no motion frames (Frames: 0)")
    i += 1
    ft = header(i, "Frame Time:")
    try:
        frame_time = float(ft)
    except ValueError:
        raise SchemaError(path, f"line {i + 1}", f"Frame Time: expected a number, got {ft!r}") from None
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise SchemaError(path, f"line {i + 1}", f"Frame Time: must be > 0, got {ft}")
    if not 1.0 / MAX_FPS <= frame_time <= 1.0 / MIN_FPS:
        raise SchemaError(
            path,
            f"line {i + 1}",
            f"Frame Time: {ft} s per frame ({1.0 / frame_time:g} fps) is outside "
            f"[{1.0 / MAX_FPS:g}, {1.0 / MIN_FPS:g}] s ({MIN_FPS:g}..{MAX_FPS:g} fps)",
        )
    i += 1
    rows = sum(1 for ln in range(i, len(lines)) if lines[ln].strip())
    if rows < F:  # before allocating [F, C]: 'Frames: 10**12' with two rows must not ask for terabytes
        raise SchemaError(
            path, f"line {len(lines)}", f"MOTION truncated: 'Frames: {F}' declared but only {rows} frame rows found"
        )

    # --- frame rows ----------------------------------------------------------------
    motion = np.empty((F, C), dtype=np.float64)
    f = 0
    for ln in range(i, len(lines)):
        s = lines[ln].split()
        if not s:
            continue
        if f >= F:
            # Real exporters are sometimes off by one (e.g. assimp's Boxing_Toes.bvh has
            # Frames: 3069 and 3070 rows): keep the declared frames, say so.
            extra = sum(1 for l in lines[ln:] if l.strip())
            warnings.warn(f"{path}: line {ln + 1}: {extra} frame row(s) beyond 'Frames: {F}' ignored", stacklevel=2)
            break
        if len(s) != C:
            raise SchemaError(
                path, f"line {ln + 1}", f"frame {f} has {len(s)} values, the hierarchy declares {C} channels"
            )
        try:
            row = np.array(s, dtype=np.float64)
        except ValueError:
            bad = next(t for t in s if not _is_float(t))
            raise SchemaError(path, f"line {ln + 1}", f"frame {f}: non-numeric value {bad!r}") from None
        if not np.all(np.isfinite(row)):
            k = int(np.argmin(np.isfinite(row)))
            raise SchemaError(path, f"line {ln + 1}", f"frame {f}: value {k} is {s[k]} (NaN/Inf)")
        motion[f] = row
        f += 1

    return BvhMotion(
        names=out["names"],
        parents=np.array(out["parents"], dtype=np.int64),
        offsets=np.array(out["offsets"], dtype=np.float64).reshape(-1, 3),
        channels=out["channels"],
        motion=motion,
        frame_time=frame_time,
        end_sites=out["end_sites"],
        path=str(path),
    )


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


# --------------------------------------------------------------------------------------
# forward kinematics
# --------------------------------------------------------------------------------------
def _axis_rotation(axis: str, deg: np.ndarray) -> np.ndarray:
    """Rotation matrices about a principal axis. deg [F] -> [F, 3, 3]."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i = "XYZ".index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    R[..., i, i] = 1.0
    R[..., j, j] = c
    R[..., k, k] = c
    R[..., j, k] = -s
    R[..., k, j] = s
    return R


def _frame_rows(bvh: BvhMotion, frames) -> np.ndarray:
    if frames is None:
        return bvh.motion
    if isinstance(frames, (int, np.integer)):
        return bvh.motion[[int(frames)]]
    return bvh.motion[frames]


def bvh_local_transforms(bvh: BvhMotion, frames: slice | np.ndarray | list[int] | int | None = None) -> np.ndarray:
    """Per-joint local transforms ``parent_from_joint``. -> [F, J, 4, 4] float64."""
    rows = _frame_rows(bvh, frames)
    F = rows.shape[0]
    J = bvh.num_joints
    T = np.zeros((F, J, 4, 4))
    T[..., 3, 3] = 1.0
    starts = bvh.channel_start()
    for j in range(J):
        R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
        t = np.broadcast_to(bvh.offsets[j], (F, 3)).copy()
        for k, ch in enumerate(bvh.channels[j]):
            v = rows[:, starts[j] + k]
            if ch.endswith("position"):
                t[:, "XYZ".index(ch[0])] += v
            else:
                R = R @ _axis_rotation(ch[0], v)
        T[:, j, :3, :3] = R
        T[:, j, :3, 3] = t
    return T


def bvh_global_transforms(bvh: BvhMotion, frames: slice | np.ndarray | list[int] | int | None = None) -> np.ndarray:
    """World transforms ``world_from_joint`` of every joint (standard BVH FK). -> [F, J, 4, 4] float64.

    ``frames``: ``None`` (all), a slice, an index array or one index. The translation
    column is the joint's world position (file units); the rotation its global rotation.
    """
    L = bvh_local_transforms(bvh, frames)
    G = np.empty_like(L)
    for j, p in enumerate(bvh.parents.tolist()):
        G[:, j] = L[:, j] if p < 0 else G[:, p] @ L[:, j]
    return G


def bvh_joint_positions(bvh: BvhMotion, frames: slice | np.ndarray | list[int] | int | None = None) -> np.ndarray:
    """World joint positions (file units). -> [F, J, 3]"""
    return bvh_global_transforms(bvh, frames)[..., :3, 3]


def bvh_rest_positions(bvh: BvhMotion) -> np.ndarray:
    """Joint positions with all channels zero (the file's rest pose, e.g. CMU's T-pose). -> [J, 3]"""
    P = np.zeros((bvh.num_joints, 3))
    for j, p in enumerate(bvh.parents.tolist()):
        P[j] = bvh.offsets[j] if p < 0 else P[p] + bvh.offsets[j]
    return P
