"""What every dataset layout reader returns (:class:`ImportedSource`) and the parsing the layouts share:
source paths that may not escape the source folder, a source calibration in any of the published
spellings, camera names made plain, and ``missing_img_files.txt``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from gsavatar.data_schema.capture import Camera, parse_calibration
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.paths import check_name, check_regular_file, is_inside


def source_path(root: Path, rel: str) -> Path:
    """``root / rel`` (symlinks and ``..`` resolved), refused (SchemaError) when it resolves outside ``root``:
    nothing in a source (a camera key like ``../../etc``, a link) may make the importer read elsewhere."""
    p = root / rel
    if Path(rel).is_absolute() or not is_inside(p, root):
        raise SchemaError(p, "", f"resolves outside the source folder {root}")
    return p.resolve()


@dataclass
class ImportedSource:
    """A dataset capture as a layout reads it: converted cameras and where each view's files are."""

    layout: str
    root: Path
    """The source folder, resolved."""
    cameras: dict[str, Camera]
    """Capture camera name -> camera in our convention (``x_cam = R x_world + T``, OpenCV axes, pixels)."""
    source_names: dict[str, str]
    """Capture camera name -> the source's camera key (equal unless the key is not a plain name)."""
    image_pattern: str
    """Image of a view relative to ``root``, ``str.format``-ed with ``cam`` (the source key) and ``frame``."""
    mask_pattern: str
    """Mask of a view, same fields."""
    smplx_params: Path
    """The SMPL-X fit (``smpl_params.npz``)."""
    missing: set[tuple[str, int]] = field(default_factory=set)
    """Views the source lists as lost: (capture camera name, source frame)."""
    fps: float = 30.0

    def image_path(self, cam: str, frame: int) -> Path:
        return source_path(self.root, self.image_pattern.format(cam=self.source_names[cam], frame=frame))

    def mask_path(self, cam: str, frame: int) -> Path:
        return source_path(self.root, self.mask_pattern.format(cam=self.source_names[cam], frame=frame))


class Layout(Protocol):
    """One dataset layout: a file per layout in this package, all with this signature."""

    name: str
    """``--layout`` value."""

    def detect(self, src: Path) -> bool:
        """Whether ``src`` looks like a capture of this layout (its calibration file is there)."""
        ...

    def read(self, src: Path) -> ImportedSource:
        """Read the calibration and the list of lost views; SchemaError names the file and field."""
        ...


def plain_names(keys: list[str]) -> dict[str, str]:
    """Capture name -> source key: a plain key (``gsavatar.utils.paths.check_name``: ``cam00``, a serial number)
    is kept, any other becomes ``cam{i:02d}`` (i: its position in the file), never colliding with a kept one."""
    out: dict[str, str] = {}
    bad = []
    for k in keys:
        try:
            out[check_name(k, "", "")] = k
        except SchemaError:
            bad.append(k)
    for k in bad:
        i = keys.index(k)
        name = f"cam{i:02d}"
        while name in out:
            name += "_"
        out[name] = k
    return dict(sorted(out.items(), key=lambda kv: keys.index(kv[1])))  # the file's camera order


def _flat(v, n_options: tuple[int, ...], file: Path, fld: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise SchemaError(file, fld, f"must be numbers, got {str(v)[:80]}") from None
    if a.size not in n_options:
        raise SchemaError(file, fld, f"expected {' or '.join(map(str, n_options))} numbers, got {a.size}")
    return a


def read_source_calibration(file: Path) -> tuple[dict[str, Camera], dict[str, str]]:
    """A THuman4.0/AvatarReX calibration file ``{key: {K, R, T, imgSize [w, h], distCoeff?}}`` (world-to-camera,
    ``x_cam = R x_world + T``, OpenCV axes; K and R as 3x3 or flat 9-lists, T as [3] or [3, 1]) as our cameras,
    validated by the capture schema's own checks. -> (capture name -> Camera, capture name -> source key)."""
    obj = read_json(check_regular_file(file, "calibration file"))
    if not isinstance(obj, dict) or not obj:
        raise SchemaError(file, "", "must be a non-empty object {camera: {K, R, T, imgSize}}")
    names = plain_names(list(obj))
    ours = {}
    for name, key in names.items():
        c = obj[key]
        if not isinstance(c, dict):
            raise SchemaError(file, key, "must be an object with K, R, T, imgSize")
        for k in ("K", "R", "T", "imgSize"):
            if k not in c:
                raise SchemaError(file, f"{key}.{k}", "missing")
        entry = {
            "K": _flat(c["K"], (9,), file, f"{key}.K").reshape(3, 3).tolist(),
            "R": _flat(c["R"], (9,), file, f"{key}.R").reshape(3, 3).tolist(),
            "T": _flat(c["T"], (3,), file, f"{key}.T").tolist(),
            "imgSize": c["imgSize"],
        }
        if c.get("distCoeff") is not None:
            d = _flat(c["distCoeff"], (4, 5, 8, 12, 14), file, f"{key}.distCoeff")
            if np.any(d[5:]):  # OpenCV's rational/thin-prism terms: not in our camera model
                raise SchemaError(file, f"{key}.distCoeff", f"coefficients past k3 are not supported: {d.tolist()}")
            entry["distCoeff"] = d[:5].tolist()
        ours[name] = entry
    return parse_calibration(ours, file), names


def read_missing_views(file: Path, source_names: dict[str, str]) -> set[tuple[str, int]]:
    """``missing_img_files.txt``: one lost image per line, ``.../{cam}/{frame:08d}.jpg`` (``\\`` or ``/``; the
    public loaders take the frame from the file name and the camera from its folder). A line under a camera's
    subfolder (``{cam}/mask/pha/...``) counts for that camera. -> {(capture camera name, frame)}."""
    if not file.exists():
        return set()
    by_key = {k: n for n, k in source_names.items()}
    out = set()
    text = check_regular_file(file, "list of missing images").read_text(errors="replace")
    for i, line in enumerate(text.splitlines(), 1):
        line = line.strip().replace("\\", "/")
        if not line:
            continue
        parts = [p for p in line.split("/") if p] or [""]  # a line of slashes names no file
        stem = parts[-1].rsplit(".", 1)[0]
        if not (stem.isascii() and stem.isdigit()):  # str.isdigit also takes '²', which int() refuses
            raise SchemaError(file, f"line {i}", f"{line!r}: the file name is not a frame number")
        cam = next((p for p in reversed(parts[:-1]) if p in by_key), None)
        if cam is None:
            raise SchemaError(file, f"line {i}", f"{line!r}: names no camera of the calibration")
        out.add((by_key[cam], int(stem)))
    return out
