"""Driving a trained avatar: motion input (npz / capture / BVH, resampled to the training frame rate by
:mod:`gsavatar.motion`), the streaming :class:`~gsavatar.drive.driver.Driver`, sequence metrics and the
``avatar-drive`` CLI."""

from gsavatar.drive.driver import DriveConfig, DriveFrame, Driver, FrameInputs, motion_inputs
from gsavatar.drive.motion import DrivingMotion, GroundTruth, load_driving_motion

__all__ = ["DriveConfig", "DriveFrame", "Driver", "DrivingMotion", "FrameInputs", "GroundTruth",
           "load_driving_motion", "motion_inputs"]
