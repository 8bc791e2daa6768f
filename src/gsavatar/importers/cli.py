"""``avatar-prep import``: a THuman4.0, AvatarReX or ActorsHQ capture with its SMPL-X fit, as capture format v1.

The command lives here, with the importers, so ``prep`` knows them only through this one class that
:mod:`gsavatar.prep.cli` registers as a subcommand (docs/architecture.md, docs/import.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

from gsavatar.importers.capture_import import ImportOptions, import_capture
from gsavatar.importers.layouts import LAYOUTS, ActorsHQ
from gsavatar.importers.smplx_model import load_smplx_model, load_smplx_uvs
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.outdir import claim_output_dir


@dataclass(kw_only=True)  # required flags after ImportOptions' defaulted ones
class Import(ImportOptions):
    """Import a THuman4.0 / AvatarReX / ActorsHQ capture fitted with SMPL-X as capture format v1 (docs/import.md)."""

    layout: Literal["thuman4", "avatarrex", "actorshq"]
    """Source layout."""
    src: Path
    """The source capture folder (e.g. ``THuman4.0/subject00``, ``avatarrex_zzr``, ``Actor01/Sequence1``)."""
    smplx_model: Path
    """The SMPL-X model file (user-supplied, MPI licence)."""
    out: Path
    """Output capture directory."""
    smplx_uvs: Path | None = None
    """OBJ with the SMPL-X mesh's UVs (e.g. smplx_uv.obj); default: the model file's, else avatar-prep uv-atlas."""
    force_out: bool = False
    """Write into a non-empty ``out`` that holds no capture."""
    actorshq_resolution: Literal["1x", "2x", "4x"] = "4x"
    """ActorsHQ only: the resolution folder to read (calibration, images, masks)."""

    def run(self) -> None:
        layout = LAYOUTS[self.layout]
        if isinstance(layout, ActorsHQ):
            layout = replace(layout, resolution=self.actorshq_resolution)
        elif self.actorshq_resolution != "4x":
            raise ValueError(f"--actorshq-resolution applies to --layout actorshq, not {self.layout}")
        if not Path(self.src).is_dir():
            raise SchemaError(self.src, "", "source folder not found")
        if not layout.detect(self.src):
            others = [n for n, lay in LAYOUTS.items() if lay.detect(self.src)]
            raise SchemaError(
                self.src,
                "",
                f"not a {self.layout} capture (its calibration file is missing)"
                + (f"; it looks like --layout {others[0]}" if others else ""),
            )
        src = layout.read(self.src)
        model = load_smplx_model(self.smplx_model)
        uvs = None if self.smplx_uvs is None else load_smplx_uvs(self.smplx_uvs, model)
        claim_output_dir(self.out, "capture", self.force_out, "--force-out", register=True)
        rep = import_capture(src, model, self.out, self, uvs=uvs)
        print(
            f"capture written to {self.out}: {len(rep.cameras)} cameras, {len(rep.source_frames)} frames "
            f"({len(rep.dropped)} dropped for lost views), images {'copied' if self.copy else 'linked'}"
        )
