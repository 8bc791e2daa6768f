"""Property-based fuzzing of every reader of a user's file (hypothesis; issue 23 items 3 and 4).

Each test starts from a small valid file built here (no synthetic anny capture) and applies one drawn,
structured mutation: truncation at a byte, a flipped / inserted / deleted / duplicated span, random bytes,
an empty file; for text formats a duplicated, deleted or swapped line, a number swapped for an extreme
(``1e308``, ``-1e308``, ``1e309``, huge integers, ``nan``, ``inf``) or a token of the format; for JSON a
value of another type, a duplicated / deleted / unknown key, ``NaN``/``Infinity``, nesting hundreds deep;
for npz a dropped key, another dtype (strings, objects, complex, datetimes), another shape, extreme values,
an ``.npy`` header or a zip directory claiming a huge array; for BVH ``Frames: 999999999`` and deep
joint nesting; for PNG an IHDR claiming huge dimensions.

The property (:func:`outcome`): the reader returns a valid result (checked per reader) or raises an error
that ``gsavatar.utils.cli.run_reporting_errors`` reports as bad input (``ValueError``, SchemaError among
them, or a path error) whose message names the file. It never raises anything else, returns within
:data:`DEADLINE` (hypothesis) and :data:`HANG_S` (an alarm, for a loop that never returns), and its peak
traced allocation (``tracemalloc``: Python objects and numpy arrays) stays under :data:`MAX_PEAK`. The
"huge count" cases also get a test of their own that asserts they fail fast.

Runs are reproducible (``derandomize=True``, no example database). docs/reliability.md "Fuzzed readers"
lists the targets, example counts and the crashes found.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import shutil
import signal
import struct
import tempfile
import time
import tracemalloc
import typing
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gsavatar.data_schema import load_capture
from gsavatar.data_schema.limits import MAX_MOTION_VALUE
from gsavatar.data_schema.rig import BODY_GROUPS, rig_from_json
from gsavatar.drive.motion import load_driving_motion
from gsavatar.geometry.mesh_io import read_obj, write_obj
from gsavatar.importers.capture_import import convert_mask
from gsavatar.importers.layouts.actorshq import CSV_FIELDS, read_actorshq_calibration
from gsavatar.importers.layouts.common import read_missing_views, read_source_calibration
from gsavatar.importers.smplx_model import SMPLX_JOINT_NAMES, SMPLX_PARENTS
from gsavatar.importers.smplx_params import load_smplx_params
from gsavatar.models.config import ModelConfig
from gsavatar.motion.bvh import read_bvh
from gsavatar.motion.joint_names import match_joints, read_joint_map
from gsavatar.runs.checkpoint import load_checkpoint, save_checkpoint
from gsavatar.runs.config import TrainConfig, model_config, resolve, to_json
from gsavatar.runs.load import load_run
from gsavatar.utils.cli import PATH_ERRORS
from gsavatar.utils.io import decode_mask, read_image, read_mask, write_image
from importers.fake_smplx import random_fit, rest_heads
from minimal_capture import RIG_JSON, box_template, make_minimal_capture

CLEAR_ERRORS = (ValueError, *PATH_ERRORS)
"""What ``run_reporting_errors`` turns into ``error: <message>`` and exit 2 (SchemaError is a ValueError)."""
DEADLINE = timedelta(seconds=5)
"""Per example; the files are a few KB, so a reader needs milliseconds (the margin is for a loaded CI box)."""
HANG_S = 30.0
"""Alarm per read: a reader still running after this is reported as hung."""
MAX_PEAK = 64 << 20
"""Peak traced allocation of one read of a seed-sized file (the seeds are < 64 KB)."""
FAST_S, FAST_PEAK = 2.0, 8 << 20
"""Bounds of a 'huge count' file (Frames: 999999999, an npy header claiming terabytes): refused at once."""
BVH_01_01 = Path("/usr/share/assimp/models/BVH/01_01.bvh")
BVH_SEED_FRAMES = 40
"""Frames of 01_01.bvh kept in its seed (the hierarchy is the interesting part; rows only need to exist)."""


def fuzz(examples: int) -> settings:
    """Reproducible settings: fixed examples (``derandomize``), no database, the deadline above."""
    return settings(
        max_examples=examples,
        deadline=DEADLINE,
        derandomize=True,
        database=None,
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.large_base_example,
            HealthCheck.filter_too_much,
        ],
    )


# --------------------------------------------------------------------------- the property
class ReaderHung(Exception):
    pass


@contextlib.contextmanager
def watched(max_peak: int) -> Iterator[None]:
    """Fail a block that runs past :data:`HANG_S` (an alarm) or whose peak traced allocation exceeds ``max_peak``."""

    def on_alarm(signum, frame):
        raise ReaderHung(f"reader still running after {HANG_S:g} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, HANG_S)
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. BVH rows beyond 'Frames:' are ignored with a warning
            yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak <= max_peak, f"peak allocation {peak / 2**20:.1f} MiB"


def outcome(read: Callable[[], object], *names: str, max_peak: int = MAX_PEAK):
    """``read()``'s result, or None when it raised a clear error (:data:`CLEAR_ERRORS`) naming one of ``names``.
    Any other exception propagates (the test fails with it); so does a message naming none of the files, a
    read running past :data:`HANG_S`, and a peak traced allocation above ``max_peak``."""
    with watched(max_peak):
        try:
            result = read()
        except CLEAR_ERRORS as e:
            assert any(n in str(e) for n in names), f"{type(e).__name__} names none of {names}: {e}"
            event(f"refused ({type(e).__name__})")  # pytest --hypothesis-show-statistics
            return None
    event("read")
    return result


def fails_fast(read: Callable[[], object], *names: str) -> str:
    """A 'huge count' file: refused with a clear error naming it, within FAST_S, allocating < FAST_PEAK."""
    t0 = time.perf_counter()
    with watched(FAST_PEAK), pytest.raises(CLEAR_ERRORS) as e:
        read()
    assert time.perf_counter() - t0 < FAST_S
    assert any(n in str(e.value) for n in names), str(e.value)
    return str(e.value)


def finite(*arrays) -> bool:
    return all(a is None or bool(np.isfinite(np.asarray(a, dtype=np.float64)).all()) for a in arrays)


def plausible_motion(*arrays) -> bool:
    """Finite and within +-MAX_MOTION_VALUE (radians, metres): what rotation maths and float32 survive."""
    return finite(*arrays) and all(np.abs(a).max(initial=0) <= MAX_MOTION_VALUE for a in arrays)


@contextlib.contextmanager
def scratch(root: Path) -> Iterator[Path]:
    """A fresh folder per example (hypothesis runs many examples in one test call)."""
    d = Path(tempfile.mkdtemp(dir=root))
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


# --------------------------------------------------------------------------- mutations: bytes and text
def mutate_bytes(data, raw: bytes) -> bytes:
    kind = data.draw(
        st.sampled_from(("truncate", "flip", "insert", "delete", "duplicate", "random", "empty")), label="bytes"
    )
    n = len(raw)
    if kind == "empty" or n == 0:
        return b""
    if kind == "random":
        return data.draw(st.binary(min_size=1, max_size=512), label="random bytes")
    if kind == "truncate":
        return raw[: data.draw(st.integers(0, n - 1), label="keep")]
    i = data.draw(st.integers(0, n - 1), label="at")
    if kind == "flip":
        b = bytearray(raw)
        b[i] ^= data.draw(st.integers(1, 255), label="xor")
        return bytes(b)
    if kind == "insert":
        return raw[:i] + data.draw(st.binary(min_size=1, max_size=64), label="inserted") + raw[i:]
    j = min(n, i + data.draw(st.integers(1, 256), label="span"))
    return raw[:i] + raw[j:] if kind == "delete" else raw[:j] + raw[i:j] + raw[j:]


EXTREME_TOKENS = (
    "1e308",
    "-1e308",
    "1e309",
    "-1e309",
    "4.9e-324",
    "nan",
    "NaN",
    "-nan",
    "inf",
    "-Infinity",
    "999999999",
    "-999999999",
    str(10**30),
    str(2**63),
    str(-(2**63) - 1),
    "0",
    "-0",
    "-1",
    "1_000",
    "0x1F",
    "1,5",
    "\u0663",
    "x",
    "",
)
"""Replacements for a number in a text file (``\\u0663``: an Arabic-Indic 3, which ``int()`` accepts)."""
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def mutate_text(data, text: str, vocab: tuple[str, ...] = ()) -> bytes:
    """A line-level mutation of ``text`` (``vocab``: lines/tokens of the format to insert), or a byte-level one."""
    lines = text.splitlines(keepends=True)
    kind = data.draw(
        st.sampled_from(("number", "token", "dup_line", "del_line", "swap_lines", "insert_line", "bytes")), label="text"
    )
    if kind == "bytes" or not lines:
        return mutate_bytes(data, text.encode())
    pick = lambda label: data.draw(st.integers(0, len(lines) - 1), label=label)  # noqa: E731
    if kind in ("number", "token"):
        cands = [i for i, ln in enumerate(lines) if (_NUMBER.search(ln) if kind == "number" else ln.split())]
        if not cands:
            return mutate_bytes(data, text.encode())
        i = data.draw(st.sampled_from(cands), label="line")
        toks = lines[i].split()
        where = [k for k, t in enumerate(toks) if kind == "token" or _NUMBER.fullmatch(t)] or list(range(len(toks)))
        k = data.draw(st.sampled_from(where), label="token")
        toks[k] = data.draw(st.sampled_from(EXTREME_TOKENS + vocab), label="new token")
        lines[i] = " ".join(toks) + "\n"
    elif kind == "dup_line":
        i = pick("line")
        lines.insert(i, lines[i])
    elif kind == "del_line":
        del lines[pick("line")]
    elif kind == "swap_lines":
        i, j = pick("line"), pick("other line")
        lines[i], lines[j] = lines[j], lines[i]
    else:
        lines.insert(pick("line"), data.draw(st.sampled_from(vocab or EXTREME_TOKENS), label="new line") + "\n")
    return "".join(lines).encode()


# --------------------------------------------------------------------------- mutations: JSON
def deep(levels: int, inner=0):
    v = inner
    for _ in range(levels):
        v = [v]
    return v


WEIRD_JSON = (
    None,
    True,
    False,
    "",
    "x",
    "../../etc/passwd",
    0,
    -1,
    1,
    0.5,
    2**63,
    -(2**63) - 1,
    10**30,
    1e308,
    -1e308,
    5e-324,
    float("nan"),
    float("inf"),
    float("-inf"),
    [],
    {},
    [1, 2],
    [[1, 2, 3]] * 3,
    {"a": 1},
    list(range(2000)),
    deep(200),
    "\u00e9\ud7ff",
)
"""Values of other types and extremes (``json.dumps`` writes the non-finite floats as NaN/Infinity literals)."""


def json_paths(obj, here: tuple = ()) -> Iterator[tuple]:
    yield here
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from json_paths(v, (*here, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:50]):  # long lists (frame indices, matrices) are sampled by their head
            yield from json_paths(v, (*here, i))


def _at(obj, path: tuple):
    for k in path:
        obj = obj[k]
    return obj


def mutate_json(data, obj) -> bytes:
    """A structural mutation of the JSON value ``obj``, serialised; or a byte-level one of its text."""
    obj = json.loads(json.dumps(obj))  # a copy
    kind = data.draw(
        st.sampled_from(("replace", "number", "delete", "add_key", "dup_key", "wrap", "stringify", "bytes")),
        label="json",
    )
    if kind == "bytes":
        return mutate_bytes(data, json.dumps(obj, indent=1).encode())
    paths = list(json_paths(obj))
    if kind == "number":
        numbers = [p for p in paths if isinstance(_at(obj, p), (int, float)) and not isinstance(_at(obj, p), bool)]
        paths = numbers or paths
    if kind in ("delete", "dup_key", "add_key"):
        want = dict if kind != "delete" else (dict, list)
        containers = [p for p in paths if isinstance(_at(obj, p), want) and (kind == "add_key" or _at(obj, p))]
        if not containers:
            return json.dumps(obj).encode()
        where = data.draw(st.sampled_from(containers), label="container")
        node = _at(obj, where)
        if kind == "add_key":
            node["zz_unknown"] = data.draw(st.sampled_from(WEIRD_JSON), label="value")
            return json.dumps(obj).encode()
        key = data.draw(st.sampled_from(list(node) if isinstance(node, dict) else list(range(len(node)))), label="key")
        if kind == "delete":
            del node[key]
            return json.dumps(obj).encode()
        marker = "\u0000duplicate"  # serialised as "\u0000duplicate", then renamed to the key: a key given twice
        node[marker] = data.draw(st.sampled_from(WEIRD_JSON + (node[key],)), label="second value")
        return json.dumps(obj).replace(json.dumps(marker), json.dumps(key)).encode()
    path = data.draw(st.sampled_from(paths), label="path")
    old = _at(obj, path)
    if kind == "replace" or kind == "number":
        pool = (
            (1e308, -1e308, 10**30, 2**64, -(2**63) - 1, 5e-324, float("nan"), float("inf"), 0, -1, True, None, "1")
            if kind == "number"
            else WEIRD_JSON
        )
        new = data.draw(st.sampled_from(pool), label="new value")
    elif kind == "wrap":  # written as text: json.dumps itself recurses too deep for 5000 levels
        levels = data.draw(st.sampled_from((1, 70, 5000)), label="levels")
        marker = "\u0000wrap"
        if path:
            _at(obj, path[:-1])[path[-1]] = marker
        text = json.dumps(obj if path else marker)
        return text.replace(json.dumps(marker), "[" * levels + json.dumps(old) + "]" * levels).encode()
    else:  # stringify: "1.5" for 1.5, "[...]" for a list
        new = json.dumps(old)
    if not path:
        return json.dumps(new).encode()
    _at(obj, path[:-1])[path[-1]] = new
    return json.dumps(obj).encode()


# --------------------------------------------------------------------------- mutations: npz
def npz_bytes(arrays: dict[str, np.ndarray], compressed: bool = False) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return buf.getvalue()


def lying_header_npz(arrays: dict[str, np.ndarray], key: str, shape: tuple[int, ...]) -> bytes:
    """``arrays`` with ``key``'s member replaced by an .npy header declaring ``shape`` (float64) and 64 bytes."""
    others = {k: v for k, v in arrays.items() if k != key}
    buf = io.BytesIO(npz_bytes(others))
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(buf, "a") as z:
        z.writestr(f"{key}.npy", hdr.getvalue() + bytes(64))
    return buf.getvalue()


def declare_uncompressed_size(raw: bytes, member: str, size: int) -> bytes:
    """The npz ``raw`` with the uncompressed size its zip directory declares for ``member`` set to ``size``."""
    data = bytearray(raw)
    i = 0
    while (i := data.find(b"PK\x01\x02", i)) >= 0:
        n = int.from_bytes(data[i + 28 : i + 30], "little")
        if data[i + 46 : i + 46 + n] == member.encode():
            data[i + 24 : i + 28] = size.to_bytes(4, "little")
            break
        i += 4
    return bytes(data)


def _other_dtype(a: np.ndarray, dt: str) -> np.ndarray:
    if a.dtype.kind not in "biuf" and dt not in ("object", "str"):  # e.g. AMASS's gender string
        return np.zeros(a.shape, dt if dt not in ("datetime", "struct") else "M8[s]")
    if dt == "object":
        return a.astype(object)
    if dt == "str":
        return a.astype("<U8")
    if dt == "datetime":
        return np.zeros(a.shape, "M8[s]")
    if dt == "struct":
        return np.zeros(a.shape, [("x", "<f4"), ("y", "<i2")])
    with np.errstate(all="ignore"):
        return a.astype(dt)


def _other_shape(a: np.ndarray, how: str) -> np.ndarray:
    if a.ndim == 0 and how not in ("extra_axis", "flat", "5d"):
        return np.stack([a, a])  # a scalar (fps, gender) becomes two values
    if how == "no_frames":
        return a[:0]
    if how == "one_more_frame":
        return np.concatenate([a, a[:1]]) if a.ndim else a
    if how == "one_less_frame":
        return a[:-1] if a.ndim else a
    if how == "extra_axis":
        return a[..., None]
    if how == "flat":
        return a.reshape(-1)
    if how == "scalar":
        return a.reshape(-1)[0] if a.size else np.float32(0)
    if how == "transposed":
        return a.T
    if how == "wider":
        return np.concatenate([a, a[..., :1]], axis=-1) if a.ndim and a.shape[-1] else a
    return np.zeros((1, 3, 3, 3, 3), a.dtype)  # "5d"


EXTREME_VALUES = (1e308, -1e308, np.nan, np.inf, -np.inf, 5e-324, 1e38, 4e38, 0.0, -1.0, 2.0**63)


def mutate_npz(data, arrays: dict[str, np.ndarray]) -> bytes:
    """A structural mutation of the arrays of an npz, serialised; or a byte-level one of the archive."""
    arrays = {k: np.array(v) for k, v in arrays.items()}
    kind = data.draw(
        st.sampled_from(("drop", "extra", "dtype", "shape", "value", "header", "declared", "bytes", "npy")), label="npz"
    )
    key = data.draw(st.sampled_from(sorted(arrays)), label="key")
    compressed = data.draw(st.booleans(), label="compressed")
    if kind == "bytes":
        return mutate_bytes(data, npz_bytes(arrays, compressed))
    if kind == "npy":  # a single array saved under the .npz name
        buf = io.BytesIO()
        np.save(buf, arrays[key])
        return buf.getvalue()
    if kind == "header":
        shape = data.draw(st.sampled_from(((10**6, 10**6), (2**40,), (999_999_999, 3), (0, 10**12))), label="shape")
        return lying_header_npz(arrays, key, shape)
    if kind == "declared":
        return declare_uncompressed_size(npz_bytes(arrays, True), f"{key}.npy", (3 << 30) + 17)
    if kind == "drop":
        del arrays[key]
    elif kind == "extra":
        arrays["zz_unknown"] = data.draw(
            st.sampled_from((np.zeros(3), np.array("x"), np.zeros((2, 2), object))), label="extra array"
        )
    elif kind == "dtype":
        dt = data.draw(
            st.sampled_from(
                (
                    "bool",
                    "int8",
                    "uint8",
                    "int64",
                    "uint64",
                    "float16",
                    "float64",
                    "complex64",
                    "str",
                    "object",
                    "datetime",
                    "struct",
                )
            ),
            label="dtype",
        )
        arrays[key] = _other_dtype(arrays[key], dt)
    elif kind == "shape":
        how = data.draw(
            st.sampled_from(
                (
                    "no_frames",
                    "one_more_frame",
                    "one_less_frame",
                    "extra_axis",
                    "flat",
                    "scalar",
                    "transposed",
                    "wider",
                    "5d",
                )
            ),
            label="shape",
        )
        arrays[key] = _other_shape(arrays[key], how)
    elif data.draw(st.booleans(), label="integer extremes"):  # value: int64 -2^63 (its abs() is negative)
        a = np.array(arrays[key], dtype=np.int64) if arrays[key].dtype.kind in "biuf" else arrays[key]
        if a.size and a.dtype.kind == "i":
            a.reshape(-1)[0] = data.draw(
                st.sampled_from((np.iinfo(np.int64).min, np.iinfo(np.int64).max)), label="value"
            )
        arrays[key] = a
    else:  # value
        a = arrays[key].astype(np.float64) if arrays[key].dtype.kind in "biuf" else arrays[key]
        v = data.draw(st.sampled_from(EXTREME_VALUES), label="value")
        if a.size and a.dtype.kind == "f":
            if data.draw(st.booleans(), label="everywhere"):
                a[...] = v
            else:
                a.reshape(-1)[data.draw(st.integers(0, a.size - 1), label="index")] = v
        arrays[key] = a
    return npz_bytes(arrays, compressed)


# --------------------------------------------------------------------------- seeds
def small_bvh(frames: int = 3) -> str:
    """Three joints (one with position channels, one with none), an End Site, ``frames`` rows."""
    return (
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation "
        "Xrotation\n JOINT Spine\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  JOINT Head\n"
        "  {\n   OFFSET 0 0.5 0.1\n   CHANNELS 0\n   End Site\n   {\n    OFFSET 0 0.2 0\n   }\n  }\n }\n}\n"
        f"MOTION\nFrames: {frames}\nFrame Time: 0.0333333\n"
        + "".join(f"{f * 0.1:g} 1.0 -0.5 {f} {-2 * f} 3.5 10 -20 {f * 5}\n" for f in range(frames))
    )


def cmu_bvh_head(frames: int = BVH_SEED_FRAMES) -> str | None:
    """The hierarchy and the first ``frames`` rows of CMU 01_01.bvh (None when assimp's models are missing)."""
    if not BVH_01_01.exists():
        return None
    lines = BVH_01_01.read_text().splitlines(keepends=True)
    m = next(i for i, ln in enumerate(lines) if ln.strip() == "MOTION")
    return "".join(lines[: m + 1]) + f"Frames: {frames}\n" + lines[m + 2] + "".join(lines[m + 3 : m + 3 + frames])


BVH_VOCAB = (
    "HIERARCHY",
    "ROOT Hips",
    "JOINT Extra",
    "End Site",
    "{",
    "}",
    "OFFSET 0 0 0",
    "OFFSET 1e308 0 0",
    "CHANNELS 3 Zrotation Yrotation Xrotation",
    "CHANNELS 7",
    "CHANNELS -1",
    "CHANNELS 3 Wrotation",
    "MOTION",
    "Frames: 999999999",
    "Frames: 0",
    "Frames: -3",
    "Frames: 1e3",
    "Frame Time: 1e-9",
    "Frame Time: 0",
    "Frame Time: nan",
    "Frame Time: 0.0083333",
    "Hips",
)


def nest(text: str, depth: int) -> str:
    """``text`` with ``depth`` channel-less joints nested inside its first joint."""
    opening = "".join(f"JOINT n{i}\n{{\nOFFSET 0 1 0\nCHANNELS 0\n" for i in range(depth))
    i = text.index("{") + 1
    return text[:i] + "\n" + opening + "}\n" * depth + text[i:]


def cameras_json(w: int = 32, h: int = 24) -> dict:
    """Two cameras as ``calibration.json`` holds them (the minimal capture's)."""
    from gsavatar.geometry.camera import look_at

    out = {}
    for i, ang in enumerate((0.0, 1.5)):
        R, T = look_at(np.array([3 * np.sin(ang), 0.5, 3 * np.cos(ang)]), np.array([0, 0.5, 0]))
        out[f"cam{i:02d}"] = {
            "K": [[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]],
            "R": R.tolist(),
            "T": T.tolist(),
            "distCoeff": [0.01, -0.002, 0, 0, 0],
            "imgSize": [w, h],
        }
    return out


def source_calibration_json() -> dict:
    """A THuman4.0/AvatarReX source calibration: flat K/R lists, T as [3, 1], a key that is not a plain name."""
    cams = cameras_json(96, 128)
    return {
        "22010708": {
            **cams["cam00"],
            "K": np.ravel(cams["cam00"]["K"]).tolist(),
            "T": [[t] for t in cams["cam00"]["T"]],
        },
        "cam 3": {**cams["cam01"], "R": np.ravel(cams["cam01"]["R"]).tolist()},
    }


def actorshq_csv() -> str:
    buf = io.StringIO()
    wr = csv.writer(buf)
    wr.writerow(CSV_FIELDS)
    wr.writerow(["Cam001", 96, 128, 0.1, -2.9, 0.05, 0.3, -0.2, 3.0, 1.6, 1.2, 0.5, 0.5])
    wr.writerow(["Cam002", 96, 128, -0.2, 1.4, 0.0, 2.8, 0.1, -0.4, 1.5, 1.1, 0.49, 0.51])
    return buf.getvalue()


def smplx_rig_json() -> dict:
    """The importers' SMPL-X rig (55 joints in model order, one axis-angle parameter per non-root joint)."""
    heads = rest_heads()
    joints = [
        {"name": n, "parent": None if p < 0 else SMPLX_JOINT_NAMES[p], "head": heads[j].tolist()}
        for j, (n, p) in enumerate(zip(SMPLX_JOINT_NAMES, SMPLX_PARENTS))
    ]
    params = [{"name": f"{n}.r", "joint": n, "kind": "axis_angle"} for n in SMPLX_JOINT_NAMES[1:]]
    return {"joints": joints, "pose_params": params, "groups": {BODY_GROUPS[0]: [p["name"] for p in params]}}


def png_with_size(raw: bytes, width: int, height: int) -> bytes:
    """A PNG whose IHDR claims ``width`` x ``height`` (CRC recomputed; the pixel data stays small)."""
    b = bytearray(raw)
    b[16:24] = struct.pack(">II", width, height)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])) & 0xFFFFFFFF)
    return bytes(b)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def capture(work) -> Path:
    return make_minimal_capture(work / "capture")


def write(path: Path, raw: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(raw)
    return path


# --------------------------------------------------------------------------- BVH
BVH_SEEDS = [s for s in (small_bvh(), cmu_bvh_head()) if s is not None]


def _check_bvh(m) -> None:
    assert m.num_frames >= 1 and m.motion.shape == (m.num_frames, sum(map(len, m.channels)))
    assert finite(m.motion, m.offsets) and 0 < m.frame_time and len(m.parents) == m.num_joints


@fuzz(60)
@given(data=st.data())
def test_read_bvh(work, data):
    text = data.draw(st.sampled_from(BVH_SEEDS), label="seed")
    kind = data.draw(st.sampled_from(("text", "frames", "nest")), label="bvh")
    if kind == "frames":
        n = data.draw(st.sampled_from(("999999999", str(10**12), "2", "0", "-1", "1e3", "0x10", "")), label="Frames")
        raw = re.sub(r"Frames:.*", f"Frames: {n}", text, count=1).encode()
    elif kind == "nest":
        raw = nest(text, data.draw(st.sampled_from((100, 256, 257, 3000)), label="depth")).encode()
    else:
        raw = mutate_text(data, text, BVH_VOCAB)
    with scratch(work) as d:
        path = write(d / "walk.bvh", raw)
        m = outcome(lambda: read_bvh(path), "walk.bvh")
    if m is not None:
        _check_bvh(m)


def test_bvh_huge_frame_count_fails_fast(work):
    for frames in ("999999999", str(10**12)):
        path = write(work / "huge.bvh", re.sub(r"Frames:.*", f"Frames: {frames}", small_bvh()).encode())
        assert "MOTION truncated" in fails_fast(lambda: read_bvh(path), "huge.bvh")


@fuzz(30)
@given(data=st.data())
def test_driving_motion_from_bvh(work, data):
    """The BVH retargeted onto a rig (joint matching, scale, FK) and resampled: the drive's BVH path."""
    text = data.draw(st.sampled_from(BVH_SEEDS), label="seed")
    rig = rig_from_json(RIG_JSON)
    target = data.draw(st.sampled_from((None, 30.0, 7.0)), label="target fps")
    with scratch(work) as d:
        path = write(d / "walk.bvh", mutate_text(data, text, BVH_VOCAB))
        m = outcome(lambda: load_driving_motion(path, rig, target), "walk.bvh")
    if m is not None:
        assert m.pose.shape == (m.num_frames, rig.pose_dim) and m.num_frames >= 1
        assert plausible_motion(m.pose, m.root_rotation, m.root_translation)


# --------------------------------------------------------------------------- joint map
CMU_NAMES = ["Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LowerBack", "Spine", "Spine1", "Neck", "Head"]
RIG_NAMES = ["pelvis", "left_hip", "left_knee", "spine1", "spine2", "spine3", "neck", "head"]
JOINT_MAP = {"pelvis": "Hips", "left_hip": "LeftUpLeg", "spine3": "Spine1", "head": None}


@fuzz(60)
@given(data=st.data())
def test_joint_map(work, data):
    with scratch(work) as d:
        path = write(d / "map.json", mutate_json(data, JOINT_MAP))

        def read():
            names = read_joint_map(path)
            assert isinstance(names, dict) and all(isinstance(k, str) for k in names)
            assert all(v is None or (isinstance(v, str) and v) for v in names.values())
            return match_joints(RIG_NAMES, CMU_NAMES, names, path)

        m = outcome(read, "map.json")
    if m is not None:
        assert len(set(m.rig_to_motion.values())) == len(m.rig_to_motion)  # one motion joint drives one rig joint


# --------------------------------------------------------------------------- motion npz (drive) and AMASS
def motion_arrays(frames: int = 5, pose_dim: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "pose": rng.normal(0, 0.2, (frames, pose_dim)).astype(np.float32),
        "root_rotation": rng.normal(0, 0.2, (frames, 3)).astype(np.float32),
        "root_translation": rng.normal(0, 0.2, (frames, 3)).astype(np.float32),
        "face": np.zeros((frames, 2), np.float32),
        "fps": np.float32(15.0),
    }


def _check_driving(m, pose_dim: int) -> None:
    assert m.num_frames >= 1 and m.pose.shape == (m.num_frames, pose_dim)
    assert m.root_rotation.shape == m.root_translation.shape == (m.num_frames, 3)
    assert plausible_motion(m.pose, m.root_rotation, m.root_translation) and finite(m.face) and m.fps > 0


@fuzz(60)
@given(data=st.data())
def test_driving_motion_npz(work, data):
    rig = rig_from_json(RIG_JSON)
    target = data.draw(st.sampled_from((None, 30.0)), label="target fps")
    sidecar = data.draw(st.booleans(), label="sidecar")
    with scratch(work) as d:
        path = write(d / "walk.npz", mutate_npz(data, motion_arrays()))
        if sidecar:  # read when the npz holds no fps
            write(d / "walk.json", mutate_json(data, {"fps": 15.0}))
        m = outcome(lambda: load_driving_motion(path, rig, target), "walk.npz", "walk.json")
    if m is not None:
        _check_driving(m, rig.pose_dim)


def amass_arrays(frames: int = 6) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {
        "poses": rng.normal(0, 0.3, (frames, 165)),
        "trans": rng.normal(0, 0.5, (frames, 3)),
        "mocap_frame_rate": np.array(120.0),
        "betas": np.zeros(16),
        "gender": np.array("neutral"),
    }


@fuzz(40)
@given(data=st.data())
def test_amass_npz(work, data):
    rig = rig_from_json(smplx_rig_json())
    target = data.draw(st.sampled_from((None, 30.0)), label="target fps")
    up = data.draw(st.sampled_from(("z", "y")), label="up")
    with scratch(work) as d:
        path = write(d / "dance.npz", mutate_npz(data, amass_arrays()))
        m = outcome(lambda: load_driving_motion(path, rig, target, amass_up=up), "dance.npz")
    if m is not None:
        _check_driving(m, rig.pose_dim)


def test_npz_huge_shapes_fail_fast(work):
    """An .npy header claiming 8 TB, a zip directory claiming 3 GiB: refused before anything is allocated."""
    rig = rig_from_json(RIG_JSON)
    for i, raw in enumerate(
        (
            lying_header_npz(motion_arrays(), "pose", (10**6, 10**6)),
            declare_uncompressed_size(npz_bytes(motion_arrays(), True), "pose.npy", 3 << 30),
        )
    ):
        path = write(work / f"huge{i}.npz", raw)
        assert "pose" in fails_fast(lambda: load_driving_motion(path, rig), path.name)
    path = write(work / "huge_amass.npz", lying_header_npz(amass_arrays(), "poses", (999_999_999, 165)))
    fails_fast(lambda: load_driving_motion(path, rig_from_json(smplx_rig_json())), path.name)


# --------------------------------------------------------------------------- capture (load_capture)
CAPTURE_FILES = {
    "capture.json": "json",
    "calibration.json": "json",
    "splits.json": "json",
    "template/rig.json": "json",
    "motion.npz": "npz",
    "template/skin_weights.npz": "npz",
    "template/mesh.obj": "text",
}
"""Files of a capture that load_capture reads, and how they are mutated."""


def mutated_capture(data, seed: Path, dst: Path, rel: str) -> Path:
    """A copy of ``seed`` (images and masks linked, not copied) with ``rel`` mutated."""
    for p in seed.rglob("*"):
        if p.is_file() and p.relative_to(seed).parts[0] not in ("images", "masks"):
            (dst / p.relative_to(seed)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, dst / p.relative_to(seed))
    for sub in ("images", "masks"):
        os.symlink(seed / sub, dst / sub)
    src = seed / rel
    how = CAPTURE_FILES[rel]
    if how == "json":
        raw = mutate_json(data, json.loads(src.read_text()))
    elif how == "npz":
        with np.load(src) as z:
            raw = mutate_npz(data, {k: z[k] for k in z.files})
    else:
        raw = mutate_text(data, src.read_text(), ("v 0 0 0", "vt 0.5 0.5", "f 1 2 3", "f 1/1 2/2 3/3", "vn 0 0 1"))
    write(dst / rel, raw)
    return dst


@pytest.mark.parametrize("rel", list(CAPTURE_FILES))
@fuzz(40)
@given(data=st.data())
def test_load_capture(work, capture, rel, data):
    with scratch(work) as d:
        root = mutated_capture(data, capture, d, rel)
        # a consistency error may name the file the mutated one disagrees with (num_frames vs motion.npz)
        cap = outcome(lambda: load_capture(root), Path(rel).name, "capture.json")
    if cap is not None:
        assert cap.motion.pose.shape == (cap.num_frames, cap.rig.pose_dim)
        assert plausible_motion(cap.motion.pose, cap.motion.root_rotation, cap.motion.root_translation)
        assert finite(cap.template.vertices, cap.template.skin_weights)
        assert all(finite(c.K, c.R, c.T, c.dist) for c in cap.cameras.values()) and 1.0 <= cap.fps <= 1000.0
        assert all(0 <= f < cap.num_frames for s in cap.splits.values() for f in s.frames)


# --------------------------------------------------------------------------- OBJ
@pytest.fixture(scope="module")
def obj_seed(work) -> str:
    t = box_template()
    write_obj(work / "seed.obj", t.vertices, t.faces, t.uvs, t.face_uvs)
    return (work / "seed.obj").read_text() + "vn 0 0 1\nf 1/1 2/2 4/3 3/1\nf -1/-1 -2/-2 -3/-3\ng group\ns off\n"


OBJ_VOCAB = (
    "v 0 0 0",
    "v 1e39 0 0",
    "vt 0.5",
    "vt 0.5 0.5",
    "vn nan 0 1",
    "f 1 2",
    "f 1 2 3",
    "f 1/1 2/2 3/3",
    "f 1//1 2//2 3//3",
    "f 0 1 2",
    "f -99 1 2",
    "f 1/999999999999 2/1 3/1",
    "f a b c",
    "f 1/2/3/4 5 6",
    "mtllib x.mtl",
    "# comment",
    "1/1",
    "-1",
)


@fuzz(60)
@given(data=st.data())
def test_read_obj(work, obj_seed, data):
    with scratch(work) as d:
        path = write(d / "mesh.obj", mutate_text(data, obj_seed, OBJ_VOCAB))
        mesh = outcome(lambda: read_obj(path), "mesh.obj")
    if mesh is not None:
        v, f = mesh.vertices, mesh.faces
        assert finite(v) and f.ndim == 2 and f.shape[1] == 3 and f.min() >= 0 and f.max() < len(v)
        if mesh.uvs is not None:
            assert finite(mesh.uvs) and mesh.face_uvs.shape == f.shape and 0 <= mesh.face_uvs.min()
            assert mesh.face_uvs.max() < len(mesh.uvs)


# --------------------------------------------------------------------------- images and masks
@pytest.fixture(scope="module")
def image_seeds(work) -> dict[str, bytes]:
    rng = np.random.default_rng(2)
    rgb = (rng.random((12, 10, 3)) * 255).astype(np.uint8)
    grey16 = (rng.random((12, 10)) * 65535).astype(np.uint16)
    rgba = np.dstack([rgb, np.where(rng.random((12, 10)) > 0.5, 255, 0).astype(np.uint8)])
    seeds = {
        name: cv2.imencode(ext, a)[1].tobytes()
        for name, ext, a in (
            ("rgb.png", ".png", rgb),
            ("grey16.png", ".png", grey16),
            ("rgba.png", ".png", rgba),
            ("rgb.jpg", ".jpg", rgb),
        )
    }
    write_image(work / "seed.exr", rng.random((12, 10, 3)))
    seeds["linear.exr"] = (work / "seed.exr").read_bytes()
    return seeds


def mask_seeds() -> dict[str, bytes]:
    m = np.zeros((12, 10), np.uint8)
    m[3:9, 2:8] = 255
    red = np.dstack([np.zeros_like(m), np.zeros_like(m), m])  # BGR: red on black
    rgba = np.dstack([np.full((12, 10, 3), 80, np.uint8), m])
    return {
        name: cv2.imencode(".png", a)[1].tobytes()
        for name, a in (
            ("grey.png", m),
            ("binary.png", (m > 0).astype(np.uint8)),
            ("red.png", red),
            ("alpha.png", rgba),
            ("grey16.png", m.astype(np.uint16) * 257),
        )
    }


def mutate_image(data, raw: bytes) -> bytes:
    if raw.startswith(b"\x89PNG") and data.draw(st.booleans(), label="resize header"):
        w, h = data.draw(
            st.sampled_from(((1, 1), (0, 5), (2**31 - 1, 2**31 - 1), (65536, 65536), (30000, 30000), (1, 10**9))),
            label="IHDR size",
        )
        return png_with_size(raw, w, h)
    return mutate_bytes(data, raw)


@fuzz(60)
@given(data=st.data())
def test_read_image(work, image_seeds, data):
    name = data.draw(st.sampled_from(sorted(image_seeds)), label="seed")
    keep_uint8 = data.draw(st.booleans(), label="keep_uint8")
    with scratch(work) as d:
        path = write(d / f"im_{name}", mutate_image(data, image_seeds[name]))
        img = outcome(lambda: read_image(path, keep_uint8=keep_uint8), path.name)
    if img is not None:
        assert img.ndim == 3 and img.shape[2] == 3 and img.dtype in (np.float32, np.uint8) and finite(img)


@fuzz(60)
@given(data=st.data())
def test_read_mask(work, data):
    seeds = mask_seeds()
    name = data.draw(st.sampled_from(sorted(seeds)), label="seed")
    with scratch(work) as d:
        path = write(d / f"mask_{name}", mutate_image(data, seeds[name]))
        m = outcome(lambda: read_mask(path), path.name)
    if m is not None:
        assert m.ndim == 2 and m.dtype == np.float32 and finite(m) and (m.size == 0 or 0 <= m.min() <= m.max() <= 1)


@fuzz(40)
@given(data=st.data())
def test_import_convert_mask(work, data):
    """``avatar-prep import``'s reader of a source's mask (grey JPEG / PNG) into a capture's 0/255 PNG."""
    src = cv2.imencode(".jpg", np.where(np.arange(120).reshape(12, 10) % 7 > 2, 255, 0).astype(np.uint8))[1]
    seed = data.draw(st.sampled_from((src.tobytes(), mask_seeds()["grey.png"])), label="seed")
    with scratch(work) as d:
        path = write(d / "00000003.jpg", mutate_image(data, seed))
        outcome(lambda: convert_mask(path, d / "out" / "mask.png", 10, 12), "00000003.jpg")
        if (d / "out" / "mask.png").exists():
            m = read_mask(d / "out" / "mask.png")
            assert m.shape == (12, 10) and set(np.unique(m)) <= {0.0, 1.0}


@fuzz(60)
@given(
    raw=hnp.arrays(
        dtype=st.sampled_from((np.uint8, np.uint16, np.bool_, np.int32, np.float32)),
        shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5),
    )
)
def test_decode_mask(raw):
    m = outcome(lambda: decode_mask(raw, "masks/cam00/00000000.png"), "00000000.png")
    if m is not None:
        assert m.ndim == 2 and m.dtype == np.float32 and (m.size == 0 or 0 <= m.min() <= m.max() <= 1)


def test_png_claiming_huge_size_fails_fast(work):
    raw = png_with_size(mask_seeds()["grey.png"], 2**31 - 1, 2**31 - 1)
    for name, read in (("big_image.png", read_image), ("big_mask.png", read_mask)):
        path = write(work / name, raw)
        fails_fast(lambda: read(path), name)


# --------------------------------------------------------------------------- run config.json (load_run)
class _ConfigRead(Exception):
    """Raised by the stand-in for build_net: load_run got past the config (the net is not built here)."""


def _build_net_stand_in(scene, mcfg, seed):
    raise _ConfigRead(mcfg)


def run_config_json() -> dict:
    cfg = resolve(TrainConfig(dataset=Path("dataset"), out=Path("run")))
    return {"train": to_json(cfg), "model": model_config(cfg).to_json(), "dataset_id": "0" * 64}


def _check_model_config(m: ModelConfig) -> None:
    """Every field of the ModelConfig a run's config.json gave has its annotated type (``true`` is no int)."""
    hints = typing.get_type_hints(ModelConfig)
    for name, hint in hints.items():
        v = getattr(m, name)
        if typing.get_origin(hint) is typing.Literal:
            assert v in typing.get_args(hint), (name, v)
        elif hint is bool:
            assert isinstance(v, bool), (name, v)
        elif hint is int:
            assert isinstance(v, int) and not isinstance(v, bool), (name, v)
        elif hint is float:
            assert isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v), (name, v)
        elif hint is str:
            assert isinstance(v, str), (name, v)
        else:  # hidden: tuple[int, ...]
            assert isinstance(v, tuple) and all(isinstance(h, int) and not isinstance(h, bool) for h in v), (name, v)


@fuzz(60)
@given(data=st.data())
def test_run_config(work, data):
    with scratch(work) as d:
        write(d / "run" / "config.json", mutate_json(data, run_config_json()))

        def read():
            try:
                load_run(d / "run", device="cpu")
            except _ConfigRead as done:
                return done.args[0]
            raise AssertionError("load_run returned without building the net")

        with (
            mock.patch("gsavatar.runs.load.load_scene", lambda dataset: None),
            mock.patch("gsavatar.runs.load.build_net", _build_net_stand_in),
        ):
            mcfg = outcome(read, "config.json")
    if mcfg is not None:
        _check_model_config(mcfg)


# --------------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def checkpoint_seed() -> tuple[dict, dict]:
    """(the state a ``save_checkpoint`` of a tiny module writes, the config it records)."""
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    config = {"model": {"hidden": [4], "sh_degree": 1}, "train": {"steps": 5}}
    buf = io.BytesIO()
    with mock.patch("gsavatar.runs.checkpoint.atomic_write_bytes", lambda path, b: buf.write(bytes(b))):
        save_checkpoint(
            "x.pt",
            step=3,
            config=config,
            modules={"net": net},
            optimizer=torch.optim.Adam(net.parameters()),
            extra={"note": "seed"},
        )
    return torch.load(io.BytesIO(buf.getvalue()), weights_only=True), config


def mutate_checkpoint(data, state: dict) -> bytes:
    kind = data.draw(st.sampled_from(("bytes", "field", "drop", "config")), label="checkpoint")
    state = dict(state)  # the tensors are shared with the seed, never changed
    if kind == "field":
        key = data.draw(st.sampled_from(sorted(state) + ["zz_unknown"]), label="key")
        state[key] = data.draw(
            st.sampled_from(
                (None, "x", 2, -1, 10**30, [], {}, [1], torch.zeros(2), {"a": 1}, "gsavatar-avatar-checkpoint")
            ),
            label="value",
        )
    elif kind == "drop":
        del state[data.draw(st.sampled_from(sorted(state)), label="key")]
    elif kind == "config":
        state["config"] = mutate_json(data, json.loads(state["config"])).decode("utf-8", errors="replace")
    buf = io.BytesIO()
    torch.save(state, buf)
    return mutate_bytes(data, buf.getvalue()) if kind == "bytes" else buf.getvalue()


@fuzz(50)
@given(data=st.data())
def test_load_checkpoint(work, checkpoint_seed, data):
    state, config = checkpoint_seed
    with scratch(work) as d:
        path = write(d / "latest.pt", mutate_checkpoint(data, state))
        got = outcome(
            lambda: load_checkpoint(path, config, strict_config_keys=("model",), defaults={"model": {"sh_degree": 1}}),
            "latest.pt",
        )
    if got is not None:
        assert isinstance(got["config"], dict) and got["config"].get("model") in (config["model"], {"hidden": [4]})
        assert isinstance(got["step"], int) and got["step"] >= 0 and isinstance(got["modules"], dict)


# --------------------------------------------------------------------------- importers
@fuzz(50)
@given(data=st.data())
def test_source_calibration(work, data):
    with scratch(work) as d:
        path = write(d / "calibration_full.json", mutate_json(data, source_calibration_json()))
        got = outcome(lambda: read_source_calibration(path), "calibration_full.json")
    if got is not None:
        cams, names = got
        assert set(cams) == set(names) and all(finite(c.K, c.R, c.T, c.dist) for c in cams.values())


@fuzz(50)
@given(data=st.data())
def test_actorshq_calibration(work, data):
    vocab = (
        ",".join(CSV_FIELDS),
        "Cam003,96,128,0,0,0,0,0,3,1,1,0.5,0.5",
        "Cam001,96,128",
        '"',
        ",,,",
        "Cam 4",
        "x" * 140_000,
    )  # a field over csv.field_size_limit()
    with scratch(work) as d:
        path = write(d / "calibration.csv", mutate_text(data, actorshq_csv(), vocab))
        got = outcome(lambda: read_actorshq_calibration(path), "calibration.csv")
    if got is not None:
        cams, names = got
        assert set(cams) == set(names) and all(finite(c.K, c.R, c.T) for c in cams.values())


@fuzz(40)
@given(data=st.data())
def test_missing_views(work, data):
    text = "images/cam00/00000003.jpg\r\nD:\\data\\22010708\\00000010.jpg\n22010708/mask/pha/00000011.jpg\n\n"
    names = {"cam00": "cam00", "cam01": "22010708"}
    vocab = (
        "cam00/",
        "x.jpg",
        "cam00/abc.jpg",
        "/",
        "\\",
        "cam00/-1.jpg",
        "cam00/" + "9" * 40 + ".jpg",
        "cam00/\u00b2.jpg",
        "cam00/\u0663.jpg",
    )
    with scratch(work) as d:
        path = write(d / "missing_img_files.txt", mutate_text(data, text, vocab))
        got = outcome(lambda: read_missing_views(path, names), "missing_img_files.txt")
    if got is not None:
        assert all(c in names and isinstance(f, int) and f >= 0 for c, f in got)


@fuzz(50)
@given(data=st.data())
def test_smplx_params(work, data):
    fit = random_fit(4, hand_cols=12)
    with scratch(work) as d:
        path = write(d / "smpl_params.npz", mutate_npz(data, fit))
        p = outcome(lambda: load_smplx_params(path), "smpl_params.npz")
    if p is not None:
        F = p.num_frames
        assert F >= 1 and p.betas.ndim == 1 and p.body_pose.shape == (F, 63) and p.transl.shape == (F, 3)
        assert 1 <= p.left_hand_pose.shape[1] <= 45 and p.left_hand_pose.shape[0] == F
        assert finite(p.betas, p.expression)
        assert plausible_motion(p.global_orient, p.transl, p.body_pose, p.left_hand_pose, p.right_hand_pose)


# --------------------------------------------------------------------------- the crashes found, pinned
def _exr_claiming_more_pixels(work: Path) -> Path:
    """The seed EXR with its dataWindow grown to 2305 x 2817 (the scanline chunks are not there)."""
    write_image(work / "seed.exr", np.full((12, 10, 3), 0.5))
    raw = bytearray((work / "seed.exr").read_bytes())
    at = raw.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4  # after the size field
    raw[at + 8 : at + 16] = struct.pack("<2i", 2304, 2816)
    return write(work / "grown.exr", bytes(raw))


def _exr_with_binary_attribute_name(work: Path) -> Path:
    """The seed EXR with the NUL ending its first attribute name flipped: OpenImageIO's message quotes the bytes."""
    write_image(work / "seed.exr", np.full((12, 10, 3), 0.5))
    raw = bytearray((work / "seed.exr").read_bytes())
    raw[raw.index(b"\x00", 8)] = 0x80
    return write(work / "binary.exr", bytes(raw))


def _npz_of_zip_version(work: Path) -> Path:
    """An npz whose first member's directory entry needs zip version 10.9 (zipfile: NotImplementedError)."""
    raw = bytearray(npz_bytes(motion_arrays()))
    at = raw.index(b"PK\x01\x02")
    raw[at + 6 : at + 8] = (109).to_bytes(2, "little")
    return write(work / "version.npz", bytes(raw))


def _npz_encrypted(work: Path) -> Path:
    """An npz whose first member is flagged as encrypted (zipfile: RuntimeError, password required)."""
    raw = bytearray(npz_bytes(motion_arrays()))
    raw[raw.index(b"PK\x01\x02") + 8] |= 1
    return write(work / "encrypted.npz", bytes(raw))


def _checkpoint_with(work: Path, state: dict, **changes) -> Path:
    buf = io.BytesIO()
    torch.save({**state, **changes}, buf)
    return write(work / "latest.pt", buf.getvalue())


def _run_with_model(work: Path, **model) -> Path:
    cfg = run_config_json()
    cfg["model"].update(model)
    write(work / "run" / "config.json", json.dumps(cfg).encode())
    return work / "run"


def _capture_with_rig_groups(work: Path, capture: Path, groups) -> Path:
    shutil.copytree(capture, work / "cap")
    write(work / "cap" / "template" / "rig.json", json.dumps({**RIG_JSON, "groups": groups}).encode())
    return work / "cap"


PNG_65536 = lambda: png_with_size(mask_seeds()["grey.png"], 65536, 65536)  # noqa: E731
SMPLX_RIG = lambda: rig_from_json(smplx_rig_json())  # noqa: E731
FOUND: dict[str, tuple[Callable, tuple[str, ...]]] = {
    # name: (work, capture, checkpoint seed -> a read that must raise, fragments of its message)
    "checkpoint version is a tensor (was RuntimeError: Boolean value of Tensor ... ambiguous)": (
        lambda w, c, s: lambda: load_checkpoint(_checkpoint_with(w, s[0], version=torch.zeros(2))),
        ("latest.pt", "version"),
    ),
    "checkpoint step is a string (was accepted; load_run's int() failed later)": (
        lambda w, c, s: lambda: load_checkpoint(_checkpoint_with(w, s[0], step="x")),
        ("latest.pt", "step"),
    ),
    "run config.json model field null (was accepted: init_normal_scale_ratio=None)": (
        lambda w, c, s: lambda: load_run(_run_with_model(w, init_normal_scale_ratio=None)),
        ("config.json", "model.init_normal_scale_ratio"),
    ),
    "run config.json model.hidden a string (was accepted as the digits (1, 2, 8))": (
        lambda w, c, s: lambda: load_run(_run_with_model(w, hidden="128")),
        ("config.json", "model.hidden"),
    ),
    "missing_img_files.txt line '/' (was IndexError)": (
        lambda w, c, s: lambda: read_missing_views(write(w / "missing_img_files.txt", b"/\n"), {"cam00": "cam00"}),
        ("missing_img_files.txt", "line 1"),
    ),
    "missing_img_files.txt frame '\u00b2' (was ValueError from int() naming no file)": (
        lambda w, c, s: (
            lambda: read_missing_views(
                write(w / "missing_img_files.txt", "cam00/\u00b2.jpg".encode()), {"cam00": "cam00"}
            )
        ),
        ("missing_img_files.txt", "line 1"),
    ),
    "calibration.csv with a non-UTF-8 byte (was UnicodeDecodeError)": (
        lambda w, c, s: (
            lambda: read_actorshq_calibration(write(w / "calibration.csv", b"\x80" + actorshq_csv().encode()))
        ),
        ("calibration.csv", "UTF-8"),
    ),
    "calibration.csv with a 140000-character field (was csv.Error)": (
        lambda w, c, s: (
            lambda: read_actorshq_calibration(
                write(w / "calibration.csv", (actorshq_csv() + "x" * 140_000 + "\n").encode())
            )
        ),
        ("calibration.csv", "CSV"),
    ),
    "PNG header claiming 65536 x 65536 as an image (was cv2.error)": (
        lambda w, c, s: lambda: read_image(write(w / "big.png", PNG_65536())),
        ("big.png", "OpenCV refused"),
    ),
    "PNG header claiming 65536 x 65536 as a mask (was cv2.error)": (
        lambda w, c, s: lambda: read_mask(write(w / "big.png", PNG_65536())),
        ("big.png", "OpenCV refused"),
    ),
    "PNG header claiming 65536 x 65536 as a source mask (was cv2.error)": (
        lambda w, c, s: lambda: convert_mask(write(w / "big.png", PNG_65536()), w / "m.png", 10, 12),
        ("big.png", "OpenCV refused"),
    ),
    "EXR dataWindow grown, chunks missing (was a 2817x2305 image of zeros, 99 MiB)": (
        lambda w, c, s: lambda: read_image(_exr_claiming_more_pixels(w)),
        ("grown.exr", "missing or corrupted"),
    ),
    "EXR attribute name with a non-UTF-8 byte (was UnicodeDecodeError)": (
        lambda w, c, s: lambda: read_image(_exr_with_binary_attribute_name(w)),
        ("binary.exr", "cannot decode EXR"),
    ),
    "mask of shape [0, 0, 0] (was ValueError: zero-size array, naming no file)": (
        lambda w, c, s: lambda: decode_mask(np.zeros((0, 0, 0), np.uint8), "m.png"),
        ("m.png", "no pixels"),
    ),
    "npz member needing zip version 10.9 (was NotImplementedError)": (
        lambda w, c, s: lambda: load_driving_motion(_npz_of_zip_version(w), rig_from_json(RIG_JSON)),
        ("version.npz", "cannot read npz"),
    ),
    "npz member flagged encrypted (was RuntimeError; the same gap, not drawn)": (
        lambda w, c, s: lambda: load_driving_motion(_npz_encrypted(w), rig_from_json(RIG_JSON)),
        ("encrypted.npz", "encrypted"),
    ),
    "AMASS poses of 1e308 (was LinAlgError: SVD did not converge)": (
        lambda w, c, s: (
            lambda: load_driving_motion(
                write(w / "dance.npz", npz_bytes({**amass_arrays(), "poses": np.full((6, 165), 1e308)})), SMPLX_RIG()
            )
        ),
        ("dance.npz", "poses", "beyond"),
    ),
    "AMASS poses of 4e38 (was a NaN root rotation)": (
        lambda w, c, s: (
            lambda: load_driving_motion(
                write(w / "dance.npz", npz_bytes({**amass_arrays(), "poses": np.full((6, 165), 4e38)})), SMPLX_RIG()
            )
        ),
        ("dance.npz", "poses", "beyond"),
    ),
    "motion npz face of 1e308 (was inf after the float32 conversion)": (
        lambda w, c, s: (
            lambda: load_driving_motion(
                write(w / "walk.npz", npz_bytes({**motion_arrays(), "face": np.full((5, 2), 1e308)})),
                rig_from_json(RIG_JSON),
            )
        ),
        ("walk.npz", "face", "float32"),
    ),
    "motion npz pose of 1e308 (was inf after the float32 conversion)": (
        lambda w, c, s: (
            lambda: load_driving_motion(
                write(w / "walk.npz", npz_bytes({**motion_arrays(), "pose": np.full((5, 3), 1e308)})),
                rig_from_json(RIG_JSON),
            )
        ),
        ("walk.npz", "pose", "beyond"),
    ),
    "rig.json group listing a list (was TypeError: unhashable type)": (
        lambda w, c, s: lambda: load_capture(_capture_with_rig_groups(w, c, {"torso_head": [[]]})),
        ("rig.json", "groups.torso_head"),
    ),
}


@pytest.mark.parametrize("case", list(FOUND))
def test_crash_found_by_fuzzing_is_a_clear_error(case, tmp_path, capture, checkpoint_seed):
    make, expect = FOUND[case]
    read = make(tmp_path, capture, checkpoint_seed)
    with (
        mock.patch("gsavatar.runs.load.load_scene", lambda dataset: None),
        mock.patch("gsavatar.runs.load.build_net", _build_net_stand_in),
        pytest.raises(CLEAR_ERRORS) as e,
    ):
        read()
    missing = [f for f in expect if f not in str(e.value)]
    assert not missing, f"message lacks {missing}: {e.value}"
