"""Driving a trained avatar: motion input (npz / capture / BVH, resampled to the training frame rate by
:mod:`gsavatar.motion`), the streaming :class:`~gsavatar.drive.driver.Driver`, the latent sources it draws
each frame's appearance latents from (:mod:`gsavatar.drive.sources`, one class per drive mode), sequence
metrics and the ``avatar-drive`` CLI."""

from gsavatar.drive.driver import DriveConfig, DriveFrame, Driver, FrameInputs, motion_inputs
from gsavatar.drive.motion import DrivingMotion, GroundTruth, load_driving_motion
from gsavatar.drive.sources import LATENT_SOURCES, DriveMode, LatentSource, SourceContext

__all__ = [
    "LATENT_SOURCES",
    "DriveConfig",
    "DriveFrame",
    "DriveMode",
    "Driver",
    "DrivingMotion",
    "FrameInputs",
    "GroundTruth",
    "LatentSource",
    "SourceContext",
    "load_driving_motion",
    "motion_inputs",
]
