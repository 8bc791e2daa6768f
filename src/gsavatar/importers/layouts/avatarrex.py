"""AvatarReX (Zheng et al., SIGGRAPH 2023), as its release notes (Animatable Gaussians' ``AVATARREX_DATASET.md``)
and loader (``dataset/dataset_mv_rgb.py: MvRgbDatasetAvatarReX``) read it::

    calibration_full.json        {"<serial>": {"K", "R", "T", "distCoeff", "imgSize": [w, h]}, ...}  world-to-camera
    <serial>/{f:08d}.jpg
    <serial>/mask/pha/{f:08d}.jpg    BackgroundMattingV2 alpha as grey JPEG, foreground > 128
    smpl_params.npz
    missing_img_files.txt            optional, ``.../<serial>/{f:08d}.jpg`` per line

``distCoeff`` is carried into our calibration (the public loaders ignore it; docs/import.md).
"""

from __future__ import annotations

from pathlib import Path

from gsavatar.importers.layouts.common import ImportedSource, read_missing_views, read_source_calibration, source_path


class AvatarReX:
    name = "avatarrex"

    def detect(self, src: Path) -> bool:
        return (Path(src) / "calibration_full.json").is_file()

    def read(self, src: Path) -> ImportedSource:
        root = Path(src).resolve()
        cameras, names = read_source_calibration(source_path(root, "calibration_full.json"))
        return ImportedSource(
            layout=self.name,
            root=root,
            cameras=cameras,
            source_names=names,
            image_pattern="{cam}/{frame:08d}.jpg",
            mask_pattern="{cam}/mask/pha/{frame:08d}.jpg",
            smplx_params=source_path(root, "smpl_params.npz"),
            missing=read_missing_views(source_path(root, "missing_img_files.txt"), names),
            fps=30.0,
        )
