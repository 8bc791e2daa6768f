"""Motion I/O shared by the synthetic captures, driving and the importers to come: a strict BVH reader
(:mod:`~gsavatar.motion.bvh`), retargeting BVH onto a rig (:mod:`~gsavatar.motion.retarget`) and the one
frame-rate resampler (:mod:`~gsavatar.motion.resample`)."""

from gsavatar.motion.bvh import BvhMotion, read_bvh
from gsavatar.motion.resample import ResampleTimes, resample_motion, resample_times
from gsavatar.motion.retarget import RetargetedMotion, motion_from_bvh_file, retarget_bvh

__all__ = ["BvhMotion", "ResampleTimes", "RetargetedMotion", "motion_from_bvh_file", "read_bvh", "resample_motion",
           "resample_times", "retarget_bvh"]
