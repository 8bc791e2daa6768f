"""Capture sources from real data: bodies and dataset layouts written as capture format v1.

SMPL-X bodies (``smplx_model``: the user's model file; ``smplx_params``: a fit's per-frame parameters;
``smplx_body``: template, rig, skin weights and motion; ``smplx_error``: what our LBS format loses); dataset
layouts (``layouts``: THuman4.0, AvatarReX, ActorsHQ, one file each) and ``capture_import`` (a layout's capture as
capture format v1); ``cli``: ``avatar-prep import``.
"""

from gsavatar.importers.capture_import import MASK_THRESHOLD, ImportOptions, ImportReport, import_capture
from gsavatar.importers.layouts import LAYOUTS, ImportedSource, Layout
from gsavatar.importers.smplx_body import (
    ImportedBody,
    SmplxBody,
    smplx_motion,
    smplx_rig,
    smplx_template,
    write_smplx_capture_body,
)
from gsavatar.importers.smplx_error import (
    SurfaceError,
    expression_error,
    posedirs_error,
    smplx_surface_chunks,
    topk_error,
)
from gsavatar.importers.smplx_model import (
    SMPLX_JOINT_GROUPS,
    SMPLX_JOINT_NAMES,
    SMPLX_PARENTS,
    SmplxModel,
    load_smplx_model,
    load_smplx_uvs,
)
from gsavatar.importers.smplx_params import SmplxParams, full_pose, load_smplx_params

__all__ = [
    "ImportOptions",
    "ImportReport",
    "ImportedSource",
    "LAYOUTS",
    "Layout",
    "MASK_THRESHOLD",
    "import_capture",
    "ImportedBody",
    "SMPLX_JOINT_GROUPS",
    "SMPLX_JOINT_NAMES",
    "SMPLX_PARENTS",
    "SmplxBody",
    "SmplxModel",
    "SmplxParams",
    "SurfaceError",
    "expression_error",
    "full_pose",
    "load_smplx_model",
    "load_smplx_params",
    "load_smplx_uvs",
    "posedirs_error",
    "smplx_motion",
    "smplx_rig",
    "smplx_surface_chunks",
    "smplx_template",
    "topk_error",
    "write_smplx_capture_body",
]
