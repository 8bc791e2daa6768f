"""A prepared dataset (``avatar-prep all``) as its consumers read it: one :func:`load_scene` for the
static artifacts, one reader per kind of per-frame texture.

The file layout, stage records and shards are :mod:`gsavatar.data_schema.dataset`; the artifact types
are :mod:`~gsavatar.data_schema.hierarchy`, :mod:`~gsavatar.data_schema.localization` and
:mod:`~gsavatar.data_schema.pose_pca`. Training (:mod:`gsavatar.train.data`), run loading
(:mod:`gsavatar.runs`) and driving read a dataset through this module only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from gsavatar.data_schema.capture import Capture, load_capture
from gsavatar.data_schema.dataset import ShardReader, read_dataset_json, stage_dir, stage_path
from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.data_schema.localization import LocalizationMasks
from gsavatar.data_schema.pose_pca import PosePCA
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_image

TextureSource = Literal["projected", "gt"]
"""Encoder input: the ``project-uv`` stage's textures, or (synthetic captures) the ground-truth albedo."""


@dataclass
class PreparedScene:
    """Everything static a model needs from a prepared dataset."""

    capture: Capture
    hierarchy: Hierarchy
    masks: LocalizationMasks
    pca_local: PosePCA
    pca_global: PosePCA
    dataset: Path
    tex_size: int

    @property
    def face_dim(self) -> int:
        f = self.capture.motion.face
        return 0 if f is None else int(f.shape[1])


def load_scene(dataset: str | Path) -> PreparedScene:
    """Load capture + prep outputs; SchemaError names a missing stage."""
    dataset = Path(dataset)
    meta = read_dataset_json(dataset)
    if not meta.get("capture"):
        raise SchemaError(dataset / "dataset.json", "capture", "not a prepared dataset: run `avatar-prep all` first")
    cap = load_capture(meta["capture"])
    h = Hierarchy.load(stage_path(dataset, "sample-points", "hierarchy.npz"))
    m = LocalizationMasks.load(stage_path(dataset, "localize", "masks.npz"))
    pl = PosePCA.load(stage_path(dataset, "fit-pca", "local.npz"))
    pg = PosePCA.load(stage_path(dataset, "fit-pca", "global.npz"))
    tex = int(meta["stages"]["project-uv"]["config"]["tex_size"])
    return PreparedScene(cap, h, m, pl, pg, dataset, tex)


# --------------------------------------------------------------------------- per-frame textures
class ProjectedTextures:
    """The ``project-uv`` stage's fused UV texture of every frame (the appearance encoder's input).

    Opens the stage's shards of ``dataset`` (SchemaError if the stage is missing); shards are read on demand.
    """

    def __init__(self, dataset: str | Path) -> None:
        self.reader = ShardReader(stage_dir(Path(dataset), "project-uv"))

    @property
    def frames(self) -> list[int]:
        """Frames with a texture, ascending."""
        return self.reader.frames

    def get(self, frame: int) -> np.ndarray:
        """Texture of ``frame``, float32 in [0, 1] (stored as float16: the conversion is exact).  # [S, S, 3]"""
        return self.reader.get(frame)["texture"].astype(np.float32)


def resize_face_mask(face_uv_mask: np.ndarray, size: int) -> np.ndarray:
    """Resize a UV face mask (True = face, top row = v=1) to ``size x size``. -> bool."""
    m = np.asarray(face_uv_mask, dtype=np.float32)
    if m.shape == (size, size):
        return m > 0.5
    if m.shape[0] >= size and m.shape[1] >= size:  # downsample: texel is face if >= half of it is
        return cv2.resize(m, (size, size), interpolation=cv2.INTER_AREA) >= 0.5
    return cv2.resize(m, (size, size), interpolation=cv2.INTER_NEAREST) > 0.5


def load_gt_texture(capture_root: Path, frame: int, size: int) -> np.ndarray | None:
    """A synthetic capture's ground-truth albedo of ``frame`` (``gt/textures``) at ``size``, or None
    when the capture has none.  # [size, size, 3] float32"""
    p = capture_root / "gt" / "textures" / f"{frame:08d}.png"
    if not p.exists():
        return None
    t = read_image(p)
    if t.shape[0] != size:
        t = cv2.resize(t, (size, size), interpolation=cv2.INTER_AREA)
    return t


class GroundTruthTextures:
    """Ground-truth albedo of a synthetic capture (``gt/textures``) at the prepared texture size, with the
    face blanked as in the projected textures (the oracle encoder input)."""

    def __init__(self, scene: PreparedScene) -> None:
        self.capture = scene.capture
        self.size = scene.tex_size
        self._face_region: np.ndarray | None = None  # [S, S] bool, built on first use

    def get(self, frame: int) -> np.ndarray:
        """Texture of ``frame``; SchemaError naming the missing file.  # [S, S, 3] float32"""
        S = self.size
        tex = load_gt_texture(self.capture.root, frame, S)
        if tex is None:
            raise SchemaError(
                self.capture.root / "gt" / "textures" / f"{frame:08d}.png",
                "texture_source",
                "texture_source='gt' needs a synthetic capture's ground-truth textures (gt/textures/*.png)",
            )
        fm = self.capture.template.face_uv_mask
        if fm is not None:
            if self._face_region is None:
                self._face_region = resize_face_mask(fm, S)
            tex = np.where(self._face_region[..., None], 0.0, tex).astype(np.float32)
        return tex


def frame_textures(
    scene: PreparedScene, source: TextureSource = "projected"
) -> ProjectedTextures | GroundTruthTextures:
    """The reader of ``scene``'s encoder-input textures for ``source``."""
    if source == "projected":
        return ProjectedTextures(scene.dataset)
    if source == "gt":
        return GroundTruthTextures(scene)
    raise ValueError(f"texture_source must be 'projected' or 'gt', got {source!r}")
