"""Capture format v1 (input contract), versioned derived datasets written by prep, every artifact type
with its load/save (rig, template, hierarchy, localization masks, pose PCA, texture shards) and the one
prepared-dataset reader (:func:`load_scene`). ``SchemaError`` (defined in :mod:`gsavatar.utils.errors`,
the lowest layer, so ``utils`` can raise it) is exported here as the schema's error type."""

from gsavatar.data_schema.capture import (
    CAPTURE_FORMAT,
    CAPTURE_VERSION,
    Camera,
    Capture,
    Motion,
    Split,
    check_images,
    load_capture,
    write_capture_metadata,
)
from gsavatar.data_schema.prepared import PreparedScene, load_scene
from gsavatar.data_schema.rig import BODY_GROUPS, Joint, PoseParam, Rig, load_rig, rig_from_json
from gsavatar.data_schema.template import Template, load_template, save_template
from gsavatar.utils.errors import SchemaError

__all__ = [
    "BODY_GROUPS",
    "CAPTURE_FORMAT",
    "CAPTURE_VERSION",
    "Camera",
    "Capture",
    "Joint",
    "Motion",
    "PoseParam",
    "PreparedScene",
    "Rig",
    "SchemaError",
    "Split",
    "Template",
    "check_images",
    "load_capture",
    "load_rig",
    "load_scene",
    "load_template",
    "rig_from_json",
    "save_template",
    "write_capture_metadata",
]
