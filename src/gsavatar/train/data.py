"""Training data: a prepared dataset (``avatar-prep all``) -> typed per-view samples.

One sample is one (frame, camera) pair: the frame's pose, root motion, face embedding and
projected UV texture (encoder input), and that camera's image, mask and intrinsics.
Distorted cameras are undistorted once per camera (cv2 remap), so the pinhole Gaussian
rasterizer sees the same geometry; images can be downscaled for CPU training.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from gsavatar.data_schema.prepared import GroundTruthTextures, PreparedScene, frame_textures
from gsavatar.data_schema.views import UndistortMaps, load_view, scaled_camera


class ViewDataset(Dataset):
    """(frame, camera) samples of one split. Items are dicts of tensors (see :meth:`__getitem__`)."""

    def __init__(
        self,
        scene: PreparedScene,
        split: str = "train",
        cameras: list[str] | None = None,
        frames: list[int] | None = None,
        image_scale: float = 1.0,
        with_texture: bool = True,
        texture_source: str = "projected",
        cache_bytes: int = 0,
    ) -> None:
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
        self._tex = None  # reader of the encoder-input textures (data_schema.prepared), opened on first use
        self._gt: GroundTruthTextures | None = None
        self._undistort = UndistortMaps()
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
        if self._tex is None:  # opened lazily: one reader (and shard cache) per DataLoader worker
            self._tex = frame_textures(self.scene, self.texture_source)
        return self._tex.get(frame)

    def gt_texture(self, frame: int) -> np.ndarray:
        """Ground-truth albedo of a synthetic capture (``gt/textures``), at the prepared texture size, with the
        face blanked as in the projected textures.  # [S, S, 3] float32"""
        if self._gt is None:
            self._gt = GroundTruthTextures(self.scene)
        return self._gt.get(frame)

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
        both = self._cache_get(
            ("view", frame, cam),
            lambda: np.concatenate(
                [
                    a.reshape(geo.height, geo.width, -1)
                    for a in load_view(
                        c.cameras[cam], c.image_path(cam, frame), c.mask_path(cam, frame), geo, self._undistort
                    )
                ],
                axis=2,
            ),
        )
        img, msk = both[..., :3], both[..., 3]
        return {
            **self.frame_inputs(frame),
            "image": torch.from_numpy(img).permute(2, 0, 1).contiguous(),  # [3, h, w] in [0, 1]
            "mask": torch.from_numpy(msk)[None],  # [1, h, w] in [0, 1]
            "viewmat": torch.from_numpy(geo.cam_from_world),  # [4, 4] cam_from_world
            "K": torch.from_numpy(geo.K),  # [3, 3]
            "cam_index": torch.tensor(self.cameras.index(cam)),
        }
