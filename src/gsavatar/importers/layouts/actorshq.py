"""ActorsHQ (Işık et al., "HumanRF", SIGGRAPH 2023), one ``ActorXX/SequenceY`` folder, as the HumanRF toolbox
(``actorshq/dataset/camera_data.py``, ``actorshq/dataset/volumetric_dataset.py``) reads it::

    {1x,2x,4x}/calibration.csv                         name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py per camera
    {res}/rgbs/{cam}/{cam}_rgb{f:06d}.jpg
    {res}/masks/{cam}/{cam}_mask{f:06d}.png            grey (or RGB, first channel) PNG, foreground > 128
    smpl_params.npz                                    SMPL-X fit (gsavatar.importers.smplx_params)

``calibration.csv`` is camera-to-world (``x_world = R(rx,ry,rz) x_cam + (tx,ty,tz)``, right-down-forward axes
as OpenCV's) with intrinsics normalised by the image size (``fx * w``, ``fy * h``, ``px * w``, ``py * h`` pixels);
:func:`read_actorshq_calibration` converts it to our world-to-camera pixel cameras. No list of lost views.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from gsavatar.data_schema.capture import Camera, parse_calibration
from gsavatar.geometry.rotations import axis_angle_to_matrix
from gsavatar.importers.layouts.common import ImportedSource, plain_names, source_path
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.paths import check_regular_file

CSV_FIELDS = ("name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py")
"""The header of ``calibration.csv`` (HumanRF's ``write_calibration_csv``)."""
ACTORSHQ_FPS = 25.0
"""ActorsHQ's capture rate (HumanRF paper: 160 cameras at 25 fps)."""


def actorshq_camera_entry(row: dict[str, float]) -> dict:
    """One ``calibration.csv`` row (numbers) -> our calibration entry ``{K, R, T, imgSize}``:
    ``R = R_c2w^T`` (``cam_from_world``), ``T = -R @ position``, ``K`` in pixels. Float64 throughout."""
    w, h = row["w"], row["h"]
    aa = torch.tensor([row["rx"], row["ry"], row["rz"]], dtype=torch.float64)
    world_from_cam = axis_angle_to_matrix(aa).numpy()  # [3, 3]
    position = np.array([row["tx"], row["ty"], row["tz"]])  # [3] camera centre in the world, metres
    cam_from_world = world_from_cam.T
    K = np.array([[row["fx"] * w, 0.0, row["px"] * w], [0.0, row["fy"] * h, row["py"] * h], [0.0, 0.0, 1.0]])
    return {
        "K": K.tolist(),
        "R": cam_from_world.tolist(),
        "T": (-cam_from_world @ position).tolist(),
        "imgSize": [int(w), int(h)],
    }


def read_actorshq_calibration(file: Path) -> tuple[dict[str, Camera], dict[str, str]]:
    """An ActorsHQ ``calibration.csv`` as our cameras (``x_cam = R x_world + T``, OpenCV axes, pixels, metres),
    validated by the capture schema's own checks. -> (capture name -> Camera, capture name -> source name)."""
    try:
        rows = _csv_rows(file)
    except UnicodeDecodeError:
        raise SchemaError(file, "", "not a UTF-8 text file") from None
    except csv.Error as e:  # e.g. a field over csv.field_size_limit(); not a ValueError
        raise SchemaError(file, "", f"not a readable CSV file: {e}") from None
    if not rows:
        raise SchemaError(file, "", "lists no camera")
    names = plain_names(list(rows))
    return parse_calibration({n: actorshq_camera_entry(rows[k]) for n, k in names.items()}, file), names


def _csv_rows(file: Path) -> dict[str, dict[str, float]]:
    """Camera name -> the numbers of its ``calibration.csv`` row (SchemaError naming the line and column)."""
    with check_regular_file(file, "calibration file").open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or [f.strip() for f in reader.fieldnames] != list(CSV_FIELDS):
            raise SchemaError(file, "header", f"expected {','.join(CSV_FIELDS)}, got {reader.fieldnames}")
        rows: dict[str, dict[str, float]] = {}
        for i, raw in enumerate(reader, 2):
            raw = {k.strip(): v for k, v in raw.items() if k is not None}
            key = (raw.get("name") or "").strip()
            if not key:
                raise SchemaError(file, f"line {i}", "camera name is empty")
            if key in rows:
                raise SchemaError(file, f"line {i}", f"camera {key!r} listed twice")
            nums = {}
            for k in CSV_FIELDS[1:]:
                try:
                    nums[k] = float(raw.get(k) or "")
                except ValueError:
                    raise SchemaError(file, f"line {i}.{k}", f"must be a number, got {raw.get(k)!r}") from None
                if not np.isfinite(nums[k]):
                    raise SchemaError(file, f"line {i}.{k}", f"must be finite, got {raw.get(k)!r}")
            for k in ("w", "h"):
                if nums[k] != int(nums[k]) or nums[k] <= 0:
                    raise SchemaError(file, f"line {i}.{k}", f"must be a positive integer, got {raw.get(k)!r}")
            rows[key] = nums
    return rows


@dataclass(frozen=True)
class ActorsHQ:
    resolution: Literal["1x", "2x", "4x"] = "4x"
    """Which of the release's resolution folders to read (calibration, images and masks all from it)."""
    name = "actorshq"

    def detect(self, src: Path) -> bool:
        return (Path(src) / self.resolution / "calibration.csv").is_file()

    def read(self, src: Path) -> ImportedSource:
        root = Path(src).resolve()
        res = self.resolution
        cameras, names = read_actorshq_calibration(source_path(root, f"{res}/calibration.csv"))
        return ImportedSource(
            layout=self.name,
            root=root,
            cameras=cameras,
            source_names=names,
            image_pattern=f"{res}/rgbs/{{cam}}/{{cam}}_rgb{{frame:06d}}.jpg",
            mask_pattern=f"{res}/masks/{{cam}}/{{cam}}_mask{{frame:06d}}.png",
            smplx_params=source_path(root, "smpl_params.npz"),
            missing=set(),
            fps=ACTORSHQ_FPS,
        )
