"""A dataset capture (any layout of :mod:`gsavatar.importers.layouts`) written as capture format v1.

- Frames: the fit's frames, optionally a ``start:stop[:step]`` slice of them (source numbering). A frame whose
  view is listed as lost (``missing_img_files.txt``) for any kept camera is dropped: the capture format has no
  per-view availability, and a camera must see every frame. ``import.json`` records which source frame each
  capture frame is and which frames were dropped for which cameras.
- Cameras: all, or ``cameras``; names made plain (a non-plain key becomes ``camNN``, recorded in import.json).
- Images: symbolic links to the source's files (resolved, checked to lie inside the source), or copies.
- Masks: the sources' grey JPEGs are decoded and written as 0/255 PNGs, foreground = value > 128
  (:data:`MASK_THRESHOLD`, the public AvatarReX snippet's), so JPEG ringing and chroma never reach the schema.
- Body: template, rig, skin weights and motion of the selected frames (:func:`write_smplx_capture_body`).
- Splits: ``test`` = the test cameras x the test frames; ``train`` = the other cameras x the other frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gsavatar.data_schema.capture import Split, check_images, load_capture, write_capture_metadata
from gsavatar.importers.layouts.common import ImportedSource
from gsavatar.importers.smplx_body import write_smplx_capture_body
from gsavatar.importers.smplx_model import SmplxModel
from gsavatar.importers.smplx_params import load_smplx_params
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_link, atomic_write_json, imread, write_image
from gsavatar.utils.paths import check_regular_file

MASK_THRESHOLD = 128
"""A source mask pixel (grey, 0..255) is foreground when > this value."""
TEST_FRAME_FRACTION = 0.1
"""Default test frames: this tail fraction of the imported frames (at least one)."""


@dataclass
class ImportOptions:
    frames: str | None = None
    """Source frames to import, ``start:stop[:step]`` (Python slice, stop exclusive); default: every frame of the
    fit."""
    cameras: tuple[str, ...] = ()
    """Cameras to import (capture or source names); default: all."""
    test_cameras: tuple[str, ...] = ()
    """Held-out cameras of the ``test`` split; default: the last imported camera."""
    test_frames: str | None = None
    """Held-out source frames, ``start:stop[:step]``; default: the last 10% of the imported frames (at least one)."""
    copy: bool = False
    """Copy the images instead of linking them (symbolic links to the resolved source files)."""
    flat_hand_mean: bool = True
    """As the fit's ``smplx.SMPLX(flat_hand_mean=...)`` (the THuman4.0/AvatarReX loaders use True)."""


class ImportReport(NamedTuple):
    source_frames: list[int]
    """Source frame of each capture frame."""
    dropped: dict[int, list[str]]
    """Source frame -> kept cameras whose view of it is lost."""
    cameras: dict[str, str]
    """Capture camera name -> source key."""
    splits: dict[str, Split]


def parse_slice(text: str, what: str) -> slice:
    """``"a:b[:c]"`` (each part optional, integers) or ``"a"`` (one frame) -> slice."""
    parts = text.split(":")
    try:
        nums = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ValueError(f"{what} must be start:stop[:step] (integers), got {text!r}") from None
    if len(nums) == 1 and nums[0] is not None:
        return slice(nums[0], nums[0] + 1)
    if not 2 <= len(nums) <= 3 or (len(nums) == 3 and nums[2] is not None and nums[2] <= 0):
        raise ValueError(f"{what} must be start:stop[:step] with a positive step, got {text!r}")
    return slice(*nums)


def select_cameras(src: ImportedSource, wanted: tuple[str, ...], what: str) -> list[str]:
    """Capture camera names for ``wanted`` (capture or source names), in the calibration's order."""
    by_source = {k: n for n, k in src.source_names.items()}
    out = []
    for w in wanted:
        name = w if w in src.cameras else by_source.get(w)
        if name is None:
            raise ValueError(
                f"{what}: unknown camera {w!r}; the calibration has {', '.join(src.source_names.values())}"
            )
        out.append(name)
    return [c for c in src.cameras if c in out]


def plan_views(
    src: ImportedSource, num_fit_frames: int, opts: ImportOptions
) -> tuple[list[str], list[int], dict[int, list[str]]]:
    """(cameras, kept source frames, dropped source frame -> cameras whose view is lost)."""
    cams = select_cameras(src, opts.cameras, "--cameras") if opts.cameras else list(src.cameras)
    frames = list(range(num_fit_frames))
    if opts.frames is not None:
        frames = frames[parse_slice(opts.frames, "--frames")]
    dropped: dict[int, list[str]] = {}
    for f in frames:
        lost = [c for c in cams if (c, f) in src.missing]
        if lost:
            dropped[f] = lost
    kept = [f for f in frames if f not in dropped]
    if not kept:
        raise ValueError(f"no frame left to import: {len(frames)} selected, {len(dropped)} with a lost view")
    return cams, kept, dropped


def make_splits(src: ImportedSource, cams: list[str], kept: list[int], opts: ImportOptions) -> dict[str, Split]:
    """Disjoint train/test splits in capture frame indices (position in ``kept``)."""
    test_cams = select_cameras(src, opts.test_cameras, "--test-cameras") if opts.test_cameras else cams[-1:]
    outside = [c for c in test_cams if c not in cams]
    if outside:
        raise ValueError(f"--test-cameras: {outside[0]!r} is not among the imported cameras")
    if opts.test_frames is None:
        test_idx = list(range(len(kept) - max(1, round(TEST_FRAME_FRACTION * len(kept))), len(kept)))
    else:
        s = parse_slice(opts.test_frames, "--test-frames")
        wanted = set(range(max(kept) + 1)[s])
        test_idx = [i for i, f in enumerate(kept) if f in wanted]
    train_cams = [c for c in cams if c not in test_cams]
    train_idx = [i for i in range(len(kept)) if i not in set(test_idx)]
    if not test_idx or not train_idx or not train_cams:
        raise ValueError(
            f"the split leaves {len(train_cams)} train cameras, {len(train_idx)} train frames and "
            f"{len(test_idx)} test frames of {len(kept)} imported; each must be at least one"
        )
    return {"train": Split(train_idx, train_cams), "test": Split(test_idx, test_cams)}


def convert_mask(src_file: Path, dst_file: Path, width: int, height: int) -> None:
    """A source's grey JPEG mask -> a 0/255 PNG (foreground > :data:`MASK_THRESHOLD`)."""
    import cv2

    raw = imread(check_regular_file(src_file, "mask file"), cv2.IMREAD_GRAYSCALE, "mask")
    if raw.shape != (height, width):
        raise SchemaError(src_file, "size", f"is {raw.shape[1]}x{raw.shape[0]}, the calibration says {width}x{height}")
    write_image(dst_file, (raw > MASK_THRESHOLD).astype(np.float32))


def import_capture(
    src: ImportedSource,
    model: SmplxModel,
    out: str | Path,
    opts: ImportOptions = ImportOptions(),
    *,
    uvs: tuple[np.ndarray, np.ndarray] | None = None,
    check: bool = True,
) -> ImportReport:
    """Write ``src`` as capture format v1 into ``out`` (claimed by the caller); validate it unless not ``check``."""
    out = Path(out)
    params = load_smplx_params(check_regular_file(src.smplx_params, "SMPL-X fit"))
    cams, kept, dropped = plan_views(src, params.num_frames, opts)
    splits = make_splits(src, cams, kept, opts)
    views = [(c, f) for c in cams for f in kept]
    for c, f in views:  # every file before the first write: a wrong layout fails fast, naming a file
        for p in (src.image_path(c, f), src.mask_path(c, f)):
            if not p.is_file():
                raise SchemaError(
                    p,
                    "",
                    f"missing (camera {src.source_names[c]!r}, frame {f}) and not listed in "
                    "missing_img_files.txt; choose frames with --frames or cameras with --cameras",
                )
    index = {f: i for i, f in enumerate(kept)}  # source frame -> capture frame
    for c, f in views:
        i, cam = index[f], src.cameras[c]
        atomic_link(src.image_path(c, f), out / "images" / c / f"{i:08d}.jpg", "copy" if opts.copy else "symlink")
        convert_mask(src.mask_path(c, f), out / "masks" / c / f"{i:08d}.png", cam.width, cam.height)
    write_smplx_capture_body(out, model, params.frames(np.array(kept)), uvs=uvs, flat_hand_mean=opts.flat_hand_mean)
    write_capture_metadata(out, src.fps, len(kept), {c: src.cameras[c] for c in cams}, splits)
    names = {c: src.source_names[c] for c in cams}
    atomic_write_json(
        out / "import.json",
        {
            "format": "gsavatar-import",
            "version": 1,
            "layout": src.layout,
            "source": str(src.root),
            "cameras": names,
            "source_frames": kept,
            "dropped_frames": {str(f): v for f, v in dropped.items()},
            "images": "copy" if opts.copy else "symlink",
            "mask_threshold": MASK_THRESHOLD,
        },
    )
    if check:
        check_images(load_capture(out))
    return ImportReport(kept, dropped, names, splits)
