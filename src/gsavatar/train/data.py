"""Training data: a prepared dataset (``avatar-prep all``) -> typed per-view samples.

One sample is one (frame, camera) pair: the frame's pose, root motion, face embedding and
projected UV texture (encoder input), and that camera's image, mask and intrinsics.
Distorted cameras are undistorted once per camera (cv2 remap), so the pinhole Gaussian
rasterizer sees the same geometry; images can be downscaled for CPU training.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from gsavatar.data_schema import Camera, Capture, load_capture
from gsavatar.data_schema.dataset import ShardReader, read_dataset_json, stage_path
from gsavatar.prep.common import stage_dir
from gsavatar.prep.localize import LocalizationMasks
from gsavatar.prep.pca import PosePCA
from gsavatar.prep.sample_points import Hierarchy
from gsavatar.utils.io import read_image, read_mask


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
        from gsavatar.data_schema import SchemaError

        raise SchemaError(dataset / "dataset.json", "capture", "not a prepared dataset: run `avatar-prep all` first")
    cap = load_capture(meta["capture"])
    h = Hierarchy.load(stage_path(dataset, "sample-points", "hierarchy.npz"))
    m = LocalizationMasks.load(stage_path(dataset, "localize", "masks.npz"))
    pl = PosePCA.load(stage_path(dataset, "fit-pca", "local.npz"))
    pg = PosePCA.load(stage_path(dataset, "fit-pca", "global.npz"))
    tex = int(meta["stages"]["project-uv"]["config"]["tex_size"])
    return PreparedScene(cap, h, m, pl, pg, dataset, tex)


@dataclass(frozen=True)
class ViewGeometry:
    """A camera as the rasterizer needs it after undistortion and resizing."""

    cam_from_world: np.ndarray  # [4, 4] float32
    K: np.ndarray  # [3, 3] float32, pixels of the resized image
    width: int
    height: int


def scaled_camera(cam: Camera, scale: float) -> ViewGeometry:
    """Pinhole camera of the undistorted image resized by ``scale`` (pixel centres stay aligned)."""
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    sx, sy = w / cam.width, h / cam.height
    K = cam.K.copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return ViewGeometry(cam.cam_from_world.astype(np.float32), K.astype(np.float32), w, h)


_UNDISTORT_MAPS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def load_view(cam: Camera, image_path: Path, mask_path: Path, geo: ViewGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Image [h,w,3] and mask [h,w] float32 in [0,1], undistorted and resized to ``geo``."""
    img = read_image(image_path)
    msk = read_mask(mask_path)
    if img.shape[:2] != (cam.height, cam.width) or msk.shape != (cam.height, cam.width):
        from gsavatar.data_schema import SchemaError

        raise SchemaError(image_path, "size", f"is {img.shape[1]}x{img.shape[0]}, calibration says {cam.width}x{cam.height}")
    if np.any(cam.dist):
        key = (cam.name, cam.width, cam.height, tuple(cam.dist))
        if key not in _UNDISTORT_MAPS:
            _UNDISTORT_MAPS[key] = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1)
        mx, my = _UNDISTORT_MAPS[key]
        img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        msk = cv2.remap(msk, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if (geo.width, geo.height) != (cam.width, cam.height):
        img = cv2.resize(img, (geo.width, geo.height), interpolation=cv2.INTER_AREA)
        msk = cv2.resize(msk, (geo.width, geo.height), interpolation=cv2.INTER_AREA)
    return img, msk


class ViewDataset(Dataset):
    """(frame, camera) samples of one split. Items are dicts of tensors (see :meth:`__getitem__`)."""

    def __init__(self, scene: PreparedScene, split: str = "train", cameras: list[str] | None = None,
                 frames: list[int] | None = None, image_scale: float = 1.0, with_texture: bool = True,
                 texture_source: str = "projected", cache_bytes: int = 0) -> None:
        cap = scene.capture
        if split not in cap.splits:
            raise ValueError(f"split must be one of {sorted(cap.splits)}, got {split!r}")
        self.scene = scene
        self.frames = list(frames if frames is not None else cap.splits[split].frames)
        self.cameras = list(cameras if cameras is not None else cap.splits[split].cameras)
        if not self.frames or not self.cameras:
            raise ValueError(f"split {split!r} has no frames or cameras")
        self.items = [(f, c) for f in self.frames for c in self.cameras]
        self.geo = {c: scaled_camera(cap.cameras[c], image_scale) for c in self.cameras}
        self.with_texture = with_texture
        if texture_source not in ("projected", "gt"):
            raise ValueError(f"texture_source must be 'projected' or 'gt', got {texture_source!r}")
        self.texture_source = texture_source
        self._tex: ShardReader | None = None
        self._face_region: np.ndarray | None = None
        # Decoded views/textures kept as float16 up to cache_bytes (a 256^2 view is 0.5 MB, a 512^2 texture 1.5
        # MB): decoding PNGs was ~13% of a CPU step. Each DataLoader worker holds its own cache.
        self.cache_bytes = int(cache_bytes)
        self._cache: dict[tuple, np.ndarray] = {}
        self._cached = 0

    def _cache_get(self, key: tuple, load) -> np.ndarray:
        hit = self._cache.get(key)
        if hit is not None:
            return hit.astype(np.float32)
        arr = load()
        if self._cached + arr.size * 2 <= self.cache_bytes:
            self._cache[key] = arr.astype(np.float16)
            self._cached += arr.size * 2
            return self._cache[key].astype(np.float32)  # the same values as a later hit
        return arr

    def __len__(self) -> int:
        return len(self.items)

    def texture(self, frame: int) -> np.ndarray:
        """Encoder input: the projected (or ``gt``: ground-truth albedo) face-masked UV texture.  # [S, S, 3] float32"""
        return self._cache_get(("tex", frame), lambda: self._load_texture(frame))

    def _load_texture(self, frame: int) -> np.ndarray:
        if self.texture_source == "gt":
            return self.gt_texture(frame)
        if self._tex is None:  # opened lazily: one reader (and shard cache) per DataLoader worker
            self._tex = ShardReader(stage_dir(self.scene.dataset, "project-uv"))
        return self._tex.get(frame)["texture"].astype(np.float32)

    def gt_texture(self, frame: int) -> np.ndarray:
        """Ground-truth albedo of a synthetic capture (``gt/textures``), at the prepared texture size, with the
        face blanked as in the projected textures.  # [S, S, 3] float32"""
        from gsavatar.prep.project_uv import resize_face_mask
        from gsavatar.prep.report import load_gt_texture

        S = self.scene.tex_size
        tex = load_gt_texture(self.scene.capture.root, frame, S)
        if tex is None:
            from gsavatar.data_schema import SchemaError

            raise SchemaError(self.scene.capture.root / "gt" / "textures" / f"{frame:08d}.png", "texture_source",
                              "texture_source='gt' needs a synthetic capture's ground-truth textures (gt/textures/*.png)")
        fm = self.scene.capture.template.face_uv_mask
        if fm is not None:
            if self._face_region is None:
                self._face_region = resize_face_mask(fm, S)
            tex = np.where(self._face_region[..., None], 0.0, tex).astype(np.float32)
        return tex

    def frame_inputs(self, frame: int) -> dict[str, torch.Tensor]:
        m = self.scene.capture.motion
        out = {
            "frame": torch.tensor(frame),
            "pose": torch.from_numpy(m.pose[frame]),  # [P] rad
            "root_rotation": torch.from_numpy(m.root_rotation[frame]),  # [3] axis-angle
            "root_translation": torch.from_numpy(m.root_translation[frame]),  # [3] m
            "face": torch.from_numpy(m.face[frame]) if m.face is not None else torch.zeros(0),  # [E]
        }
        if self.with_texture:
            out["texture"] = torch.from_numpy(self.texture(frame)).permute(2, 0, 1).contiguous()  # [3, S, S]
        return out

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        frame, cam = self.items[i]
        c = self.scene.capture
        geo = self.geo[cam]
        both = self._cache_get(("view", frame, cam), lambda: np.concatenate(
            [a.reshape(geo.height, geo.width, -1) for a in
             load_view(c.cameras[cam], c.image_path(cam, frame), c.mask_path(cam, frame), geo)], axis=2))
        img, msk = both[..., :3], both[..., 3]
        return {
            **self.frame_inputs(frame),
            "image": torch.from_numpy(img).permute(2, 0, 1).contiguous(),  # [3, h, w] in [0, 1]
            "mask": torch.from_numpy(msk)[None],  # [1, h, w] in [0, 1]
            "viewmat": torch.from_numpy(geo.cam_from_world),  # [4, 4] cam_from_world
            "K": torch.from_numpy(geo.K),  # [3, 3]
            "cam_index": torch.tensor(self.cameras.index(cam)),
        }
