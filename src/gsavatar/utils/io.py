"""Atomic file writes and image IO.

Every file gsavatar writes goes through a temp file in the same directory and an
``os.replace``, so a killed process never leaves a half-written file behind under
the final name.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import tempfile
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import is_int, parse_json_text
from gsavatar.utils.paths import check_output, check_regular_file


NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""OS errors that mean the disk (or quota, or file-size limit) is full."""


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path``; move it onto ``path`` only if the block succeeds.

    ``suffix`` defaults to the final suffix so writers that pick a format from the
    extension (OpenImageIO, OpenCV, numpy) still work.
    """
    path = Path(path)
    check_output(path)  # refused before any folder is made when the path escapes the command's --out
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix, dir=path.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp creates 0600; give the final file the usual umask-based mode.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as e:
        if e.errno in NO_SPACE_ERRNOS and not e.filename:  # a write() that failed names no file: name the target
            raise OSError(e.errno, os.strerror(e.errno), str(path)) from None
        raise
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
    """``np.savez`` layout (uncompressed ``<key>.npy`` members, no pickles) with fixed member timestamps, so
    the same arrays always give the same bytes (a recomputed stage keeps its checksum and the dataset's id)."""
    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key, value in arrays.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o644 << 16
                with zf.open(info, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)


def atomic_link(target: str | Path, path: str | Path, how: str = "symlink") -> None:
    """Make ``path`` a symbolic link to ``target`` (an absolute path), a hard link to it, or a copy of it
    (``how``: "symlink", "hardlink", "copy"), replacing whatever is at ``path`` in one rename.

    Only ``path``'s folder is checked against the command's output roots: a link into a capture's source
    points outside ``--out`` by design, and replacing it replaces the link, never what it points to.
    """
    import shutil

    path = Path(path)
    if how not in ("symlink", "hardlink", "copy"):
        raise ValueError(f"how must be 'symlink', 'hardlink' or 'copy', got {how!r}")
    if path.name in ("", ".", ".."):
        raise SchemaError(path, "", "not a file name")
    check_output(path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mktemp(prefix=f".{path.name}.", suffix=".link", dir=path.parent))
    try:
        if how == "symlink":
            os.symlink(Path(target).resolve(), tmp)
        elif how == "hardlink":
            os.link(target, tmp)
        else:
            shutil.copyfile(target, tmp)
        os.replace(tmp, path)
    finally:
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


MAX_IMAGE_PIXELS = 1 << 28
"""Largest image read (268M pixels, e.g. 16k x 16k); OpenCV refuses above 2^30 pixels by itself."""


def oiio_error(geterror) -> str:
    """OpenImageIO's error text (``buf.geterror`` or ``oiio.geterror``): a message quoting the bytes of a corrupt
    header is not UTF-8, and reading it raised UnicodeDecodeError instead of naming the file."""
    try:
        return geterror()
    except UnicodeDecodeError:
        return "corrupt header (the error message is not text)"


def imread(path: Path, flags: int, what: str = "image") -> np.ndarray:
    """``cv2.imread`` of a checked regular file; SchemaError naming ``path`` when it cannot be decoded. OpenCV
    returns None for most broken files but raises ``cv2.error`` for a header claiming more than 2^30 pixels
    (a 65536 x 65536 PNG IHDR)."""
    import cv2

    try:
        raw = cv2.imread(str(path), flags)
    except cv2.error as e:
        reason = getattr(e, "err", None) or str(e).strip()
        raise SchemaError(path, "", f"cannot decode {what}: OpenCV refused it ({reason})") from None
    if raw is None:
        raise SchemaError(path, "", f"cannot decode {what} (truncated or not an image)")
    return raw


def read_image(path: str | Path, keep_uint8: bool = False) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1] (EXR: linear values as stored).  # [H, W, 3]

    ``keep_uint8``: an 8-bit file is returned as its uint8 RGB values instead (``x / 255`` in float32 is the
    float result, bit for bit); other files as float32 all the same. For consumers that convert per sample
    (project-uv's kernels): the float conversion is ~3x the JPEG decode's memory traffic.

    Raises :class:`SchemaError` naming the file when it is missing, not a regular file (checked before
    opening: a FIFO would block), larger than MAX_IMAGE_PIXELS, cannot be decoded, or holds NaN/Inf
    pixels (float EXR/TIFF; they would reach training as ``loss nan``).
    """
    path = check_regular_file(path, "image file")
    if path.suffix.lower() == ".exr":
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(str(path))
        spec = buf.spec()
        if buf.has_error:
            raise SchemaError(path, "", f"cannot decode EXR: {oiio_error(buf.geterror)}")
        if spec.width * spec.height > MAX_IMAGE_PIXELS:
            raise SchemaError(
                path, "size", f"{spec.width}x{spec.height} pixels, more than the {MAX_IMAGE_PIXELS} an image may have"
            )
        # Decode and check before the float copy: missing or corrupt scanline chunks (a header claiming 2305x2817
        # pixels in a 1 KB file) came back as an image of zeros, the error left pending.
        if not buf.read(0, 0, True) or buf.has_error:
            raise SchemaError(path, "", f"cannot decode EXR: {oiio_error(buf.geterror)}")
        arr = buf.get_pixels(oiio.FLOAT)
        if arr is None or arr.size == 0:
            raise SchemaError(path, "", f"cannot decode EXR: {oiio_error(buf.geterror)}")
        arr = np.asarray(arr, dtype=np.float32)
        if arr.ndim == 2:
            arr = arr[..., None]
    else:
        import cv2

        # JPEG: decode like every viewer does, with the EXIF orientation applied (IMREAD_UNCHANGED ignores
        # it, and a phone's portrait photo would be read sideways); check_images compares the upright size.
        jpeg = path.suffix.lower() in (".jpg", ".jpeg")
        raw = imread(path, cv2.IMREAD_COLOR if jpeg else cv2.IMREAD_UNCHANGED)
        # Channel order and grey -> RGB on the decoded integers (one SIMD pass), then one division: the same
        # values as converting first (float32 x / scale), ~5x less time on large JPEGs.
        if raw.ndim == 3 and raw.shape[2] == 1:
            raw = raw[..., 0]
        if raw.ndim == 2:
            raw = cv2.cvtColor(raw, cv2.COLOR_GRAY2RGB)
        elif raw.shape[2] >= 3:
            raw = cv2.cvtColor(raw, cv2.COLOR_BGRA2RGB if raw.shape[2] == 4 else cv2.COLOR_BGR2RGB)  # drop alpha
        else:
            raise SchemaError(path, "", f"image with {raw.shape[2]} channels (expected grey, RGB or RGBA)")
        if keep_uint8 and raw.dtype == np.uint8:
            return np.ascontiguousarray(raw)
        scale = 65535.0 if raw.dtype == np.uint16 else (1.0 if raw.dtype.kind == "f" else 255.0)
        arr = np.divide(raw, np.float32(scale), dtype=np.float32)
        if raw.dtype.kind != "f":
            return arr  # integers decode to finite values
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    arr = np.ascontiguousarray(arr[..., :3])
    bad = ~np.isfinite(arr).all(axis=-1)  # [H, W]
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise SchemaError(path, "", f"{int(bad.sum())} non-finite pixels (NaN/Inf; first at x={x}, y={y})")
    return arr


MASK_ENCODINGS = (
    "single-channel 0..255 (or 0..65535), single-channel 0/1, grey RGB (equal channels), "
    "single-colour RGB (e.g. red 255,0,0 on black), or RGBA / grey+alpha with the mask in a varying alpha"
)


def decode_mask(raw: np.ndarray, path: str | Path = "mask") -> np.ndarray:
    """A decoded mask image (OpenCV channel order) as float32 foreground in [0, 1].  # [H, W]

    Accepted encodings (:data:`MASK_ENCODINGS`, docs/data_schema.md "Masks"): the mask channel is the
    alpha channel when the image has one that varies, else the grey value, else the one colour the
    foreground is painted in. An integer channel whose maximum is 1 is a 0/1 mask. Anything else (a
    photo, channels painted in different colours, float data) is refused with SchemaError naming ``path``.
    """
    if raw.dtype not in (np.uint8, np.uint16):
        raise SchemaError(
            path, "", f"mask pixels must be 8- or 16-bit integers, got {raw.dtype}; masks are {MASK_ENCODINGS}"
        )
    if raw.size == 0:  # the reductions below have no identity for zero pixels
        raise SchemaError(path, "", f"mask of shape {list(raw.shape)} has no pixels")
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.ndim == 3:
        if raw.shape[2] in (2, 4) and raw[..., -1].min() != raw[..., -1].max():
            raw = raw[..., -1]  # varying alpha: the mask is the alpha channel
        else:
            col = raw[..., : 1 if raw.shape[2] == 2 else 3]
            m = col.max(axis=2)
            painted = [c for c in range(col.shape[2]) if col[..., c].any()]
            if not all(np.array_equal(col[..., c], m) for c in painted):
                raise SchemaError(
                    path, "", f"colour image, not a mask (its channels differ); masks are {MASK_ENCODINGS}"
                )
            raw = m
    if raw.ndim != 2:
        raise SchemaError(path, "", f"mask of shape {list(raw.shape)}; masks are {MASK_ENCODINGS}")
    peak = int(raw.max()) if raw.size else 0
    scale = 1.0 if peak == 1 else (65535.0 if raw.dtype == np.uint16 else 255.0)
    return raw.astype(np.float32) / scale


def read_mask(path: str | Path) -> np.ndarray:
    """Read a foreground mask as float32 in [0, 1] (encodings: :func:`decode_mask`).  # [H, W]

    SchemaError naming the file when it is missing, not a regular file, undecodable or not a mask."""
    import cv2

    path = check_regular_file(path, "mask file")
    raw = imread(path, cv2.IMREAD_UNCHANGED, "mask")
    return decode_mask(raw, path)


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


NPZ_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, RuntimeError)
"""What ``np.load`` and reading its arrays raise for a truncated, corrupt or pickled npz (RuntimeError: a member
flagged as encrypted; its subclass NotImplementedError: an unknown zip version or compression method)."""
MAX_NPZ_ARRAY_BYTES = 2 << 30
"""Largest array read from an npz (uncompressed): 2 GiB, 20x our largest (a paper-preset hierarchy or
localization is ~100 MB). Deflate shrinks zeros ~1000x, so a 2 MB file can hold a 2 GB array."""


def _npy_header(f) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from the header of an .npy stream, reading nothing past the header."""
    major, _ = np.lib.format.read_magic(f)
    read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    shape, _, dtype = read(f)
    return shape, dtype


def read_npz(
    path: str | Path, keys: tuple[str, ...] | list[str] | None = None, max_bytes: int = MAX_NPZ_ARRAY_BYTES
) -> dict[str, np.ndarray]:
    """The arrays of an npz (no pickles): all of them, or only those of ``keys`` that it holds (the others
    are never decompressed; callers check for missing keys with their own field names).

    Each array's size is checked before it is decompressed: its zip member's declared uncompressed size
    must be at most ``max_bytes``, and the shape in its .npy header must fit in that member. SchemaError
    names the file (and the key) when it is missing, not a regular file, not an npz archive (e.g. a single
    .npy array saved under an .npz name), truncated, corrupt (bad zip, bad CRC), too large, or holds
    object arrays or non-array members.
    """
    path = check_regular_file(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic.startswith(b"\x93NUMPY"):
            raise SchemaError(path, "", "cannot read npz: not an npz archive (it holds a single .npy array)")
        if not magic.startswith(b"PK"):
            raise SchemaError(path, "", "cannot read npz: not an npz archive (not a zip file)")
        with np.load(path, allow_pickle=False) as z:
            names = set(z.zip.namelist())
            wanted = z.files if keys is None else [k for k in dict.fromkeys(keys) if k in z.files]
            out = {}
            for k in wanted:
                member = f"{k}.npy" if f"{k}.npy" in names else k
                size = z.zip.getinfo(member).file_size
                if size > max_bytes:
                    raise SchemaError(
                        path, k, f"{size} bytes uncompressed, more than the {max_bytes} an array may have here"
                    )
                with z.zip.open(member) as m:
                    try:
                        shape, dtype = _npy_header(m)
                    except ValueError as e:
                        raise SchemaError(path, k, f"not a numpy array ({e})") from None
                if dtype.hasobject:
                    raise SchemaError(path, k, "object array (pickled data is refused)")
                nbytes = math.prod(shape) * dtype.itemsize
                if nbytes > size:
                    raise SchemaError(
                        path,
                        k,
                        f"header declares shape {list(shape)} of {dtype} ({nbytes} bytes), "
                        f"the archive holds {size} bytes",
                    )
                out[k] = z[k]
            return out
    except SchemaError:
        raise
    except NPZ_READ_ERRORS as e:
        raise SchemaError(
            path, "", f"cannot read npz (truncated, corrupt or not an npz of plain arrays): {e}"
        ) from None


def load_versioned_npz(
    path: str | Path,
    fmt: str,
    version: int,
    required: tuple[str, ...] = (),
    what: str = "gsavatar",
    keys: tuple[str, ...] | None = None,
) -> tuple[dict, dict[str, np.ndarray]]:
    """Load an npz written with a JSON ``header`` (format + version); no pickles.

    ``keys``: optional arrays to read besides ``header`` and ``required`` (None: every array).
    Returns (header, arrays). Raises SchemaError naming the file and the field for a missing
    file, unreadable npz, missing/invalid header, wrong format or version, or missing arrays.
    """
    path = Path(path)
    arrays = read_npz(path, None if keys is None else ("header", *required, *keys))
    if "header" not in arrays:
        raise SchemaError(path, "header", f"missing (not a {what} file)")
    raw = arrays.pop("header")
    if raw.dtype.kind != "U" or raw.ndim != 0:
        raise SchemaError(path, "header", f"expected a JSON string, got {raw.dtype} array of shape {list(raw.shape)}")
    hdr = parse_json_text(str(raw), path)
    if not isinstance(hdr, dict) or hdr.get("format") != fmt:
        got = hdr.get("format") if isinstance(hdr, dict) else hdr
        raise SchemaError(path, "header.format", f"expected {fmt!r}, got {got!r}")
    if not is_int(hdr.get("version")) or hdr["version"] != version:
        raise SchemaError(path, "header.version", f"unsupported version {hdr.get('version')!r} (expected {version})")
    for k in required:
        if k not in arrays:
            raise SchemaError(path, k, "missing")
    return hdr, arrays
