"""A capture camera as the pinhole rasterizer sees it: undistorted once (cv2 remap) and resized.

Used by training (:mod:`gsavatar.train.data`), run rendering and the driver's ground truth, so every
consumer sees the same pixels for the same (camera, scale).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gsavatar.data_schema.capture import Camera
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_image, read_mask


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


class UndistortMaps:
    """cv2 remap tables of distorted cameras, built once per camera by whoever holds this cache (a data
    set, a driver): building one costs about as much as decoding an image."""

    def __init__(self) -> None:
        self._maps: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def get(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y) of ``cam``: undistorted pixel -> distorted pixel.  # [H, W] float32 each"""
        key = (cam.name, cam.width, cam.height, tuple(cam.dist))
        if key not in self._maps:
            self._maps[key] = cv2.initUndistortRectifyMap(
                cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1
            )
        return self._maps[key]


def load_view(
    cam: Camera, image_path: Path, mask_path: Path, geo: ViewGeometry, maps: UndistortMaps | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Image [h,w,3] and mask [h,w] float32 in [0,1], undistorted and resized to ``geo``.

    ``maps``: the cache of undistortion tables to use (None: build this camera's table for this call)."""
    img = read_image(image_path)
    msk = read_mask(mask_path)
    if img.shape[:2] != (cam.height, cam.width) or msk.shape != (cam.height, cam.width):
        raise SchemaError(
            image_path, "size", f"is {img.shape[1]}x{img.shape[0]}, calibration says {cam.width}x{cam.height}"
        )
    if np.any(cam.dist):
        mx, my = (maps if maps is not None else UndistortMaps()).get(cam)
        img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        msk = cv2.remap(msk, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if (geo.width, geo.height) != (cam.width, cam.height):
        img = cv2.resize(img, (geo.width, geo.height), interpolation=cv2.INTER_AREA)
        msk = cv2.resize(msk, (geo.width, geo.height), interpolation=cv2.INTER_AREA)
    return img, msk
