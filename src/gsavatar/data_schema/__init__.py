"""Capture format v1 (input contract) and versioned derived datasets written by prep."""

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
from gsavatar.data_schema.errors import SchemaError
from gsavatar.data_schema.rig import BODY_GROUPS, Joint, PoseParam, Rig, load_rig, rig_from_json
from gsavatar.data_schema.template import Template, load_template, save_template

__all__ = [
    "BODY_GROUPS", "CAPTURE_FORMAT", "CAPTURE_VERSION", "Camera", "Capture", "Joint", "Motion", "PoseParam",
    "Rig", "SchemaError", "Split", "Template", "check_images", "load_capture", "load_rig", "load_template",
    "rig_from_json", "save_template", "write_capture_metadata",
]
