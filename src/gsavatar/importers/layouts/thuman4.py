"""THuman4.0 (Zheng et al., "Structured local radiance fields", CVPR 2022), as Animatable Gaussians' loader
(``dataset/dataset_mv_rgb.py: MvRgbDatasetTHuman4``) reads it::

    calibration.json         {"cam00": {"K", "R", "T", "imgSize": [w, h]}, ...}  world-to-camera, K/R flat or 3x3
    images/camNN/{f:08d}.jpg
    masks/camNN/{f:08d}.jpg  grey JPEG, foreground > 128
    smpl_params.npz          SMPL-X fit (gsavatar.importers.smplx_params)
    missing_img_files.txt    lost views, ``.../camNN/{f:08d}.jpg`` per line
"""

from __future__ import annotations

from pathlib import Path

from gsavatar.importers.layouts.common import ImportedSource, read_missing_views, read_source_calibration, source_path


class THuman4:
    name = "thuman4"

    def detect(self, src: Path) -> bool:
        return (Path(src) / "calibration.json").is_file() and (Path(src) / "images").is_dir()

    def read(self, src: Path) -> ImportedSource:
        root = Path(src).resolve()
        cameras, names = read_source_calibration(source_path(root, "calibration.json"))
        return ImportedSource(
            layout=self.name,
            root=root,
            cameras=cameras,
            source_names=names,
            image_pattern="images/{cam}/{frame:08d}.jpg",
            mask_pattern="masks/{cam}/{frame:08d}.jpg",
            smplx_params=source_path(root, "smpl_params.npz"),
            missing=read_missing_views(source_path(root, "missing_img_files.txt"), names),
            fps=30.0,
        )
