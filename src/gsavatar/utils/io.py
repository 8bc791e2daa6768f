"""Atomic file writes and image IO.

Every file gsavatar writes goes through a temp file in the same directory and an
``os.replace``, so a killed process never leaves a half-written file behind under
the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gsavatar.data_schema.errors import SchemaError


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path``; move it onto ``path`` only if the block succeeds.

    ``suffix`` defaults to the final suffix so writers that pick a format from the
    extension (OpenImageIO, OpenCV, numpy) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp creates 0600; give the final file the usual umask-based mode.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1))


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1] (EXR: linear values as stored).  # [H, W, 3]

    Raises :class:`SchemaError` naming the file when it is missing or cannot be decoded.
    """
    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "image file not found")
    if path.suffix.lower() == ".exr":
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(str(path))
        if buf.has_error:
            raise SchemaError(path, "", f"cannot decode EXR: {buf.geterror()}")
        arr = buf.get_pixels(oiio.FLOAT)
        if arr is None or arr.size == 0:
            raise SchemaError(path, "", "cannot decode EXR")
        arr = np.asarray(arr, dtype=np.float32)
        if arr.ndim == 2:
            arr = arr[..., None]
    else:
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise SchemaError(path, "", "cannot decode image (truncated or not an image)")
        scale = 65535.0 if raw.dtype == np.uint16 else 255.0
        arr = raw.astype(np.float32) / scale
        if arr.ndim == 2:
            arr = arr[..., None]
        elif arr.shape[2] >= 3:
            arr = arr[..., [2, 1, 0]]  # BGR -> RGB, drop alpha
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return np.ascontiguousarray(arr[..., :3])


def read_mask(path: str | Path) -> np.ndarray:
    """Read a foreground mask (0..255 PNG) as float32 in [0, 1].  # [H, W]"""
    import cv2

    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "mask file not found")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SchemaError(path, "", "cannot decode mask (truncated or not an image)")
    if raw.ndim == 3:
        raw = raw[..., 0]
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    return raw.astype(np.float32) / scale


def write_image(path: str | Path, img: np.ndarray) -> None:
    """Write float [0,1] RGB (or a [H,W] mask) atomically; EXR via OpenImageIO, else 8-bit.

    img: [H, W, 3] or [H, W] float
    """
    path = Path(path)
    img = np.asarray(img)
    if path.suffix.lower() == ".exr":
        import OpenImageIO as oiio

        arr = img.astype(np.float32)
        if arr.ndim == 2:
            arr = arr[..., None]  # OpenImageIO needs (H, W, C)
        with atomic_path(path) as tmp:
            out = oiio.ImageOutput.create(str(tmp))
            spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], oiio.HALF)
            out.open(str(tmp), spec)
            out.write_image(arr)
            out.close()
        return
    import cv2

    u8 = np.clip(np.rint(img.astype(np.float32) * 255.0), 0, 255).astype(np.uint8)
    if u8.ndim == 3:
        u8 = u8[..., ::-1]
    ok, enc = cv2.imencode(path.suffix.lower() or ".png", np.ascontiguousarray(u8))
    if not ok:
        raise OSError(f"could not encode {path}")
    atomic_write_bytes(path, enc.tobytes())


NPZ_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile)
"""What ``np.load`` and reading its arrays raise for a truncated, corrupt or pickled npz."""


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an npz (no pickles). SchemaError names the file when it is missing, truncated,
    corrupt (bad zip, bad CRC) or holds object arrays."""
    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except NPZ_READ_ERRORS as e:
        raise SchemaError(path, "", f"cannot read npz (truncated, corrupt or not an npz of plain arrays): {e}") from None


def load_versioned_npz(path: str | Path, fmt: str, version: int, required: tuple[str, ...] = (),
                       what: str = "gsavatar") -> tuple[dict, dict[str, np.ndarray]]:
    """Load an npz written with a JSON ``header`` (format + version); no pickles.

    Returns (header, arrays). Raises SchemaError naming the file and the field for a missing
    file, unreadable npz, missing/invalid header, wrong format or version, or missing arrays.
    """
    path = Path(path)
    arrays = read_npz(path)
    if "header" not in arrays:
        raise SchemaError(path, "header", f"missing (not a {what} file)")
    try:
        hdr = json.loads(str(arrays.pop("header")))
    except json.JSONDecodeError as e:
        raise SchemaError(path, "header", f"invalid JSON: {e.msg}") from None
    if not isinstance(hdr, dict) or hdr.get("format") != fmt:
        got = hdr.get("format") if isinstance(hdr, dict) else hdr
        raise SchemaError(path, "header.format", f"expected {fmt!r}, got {got!r}")
    if hdr.get("version") != version:
        raise SchemaError(path, "header.version", f"unsupported version {hdr.get('version')!r} (expected {version})")
    for k in required:
        if k not in arrays:
            raise SchemaError(path, k, "missing")
    return hdr, arrays
