"""Motion I/O shared by the synthetic captures, driving and the importers: a strict BVH reader
(:mod:`~gsavatar.motion.bvh`), retargeting BVH onto any rig (:mod:`~gsavatar.motion.retarget`, joint names
matched by :mod:`~gsavatar.motion.joint_names`, rig parameters solved by :mod:`~gsavatar.motion.rig_pose`),
AMASS-style SMPL-X motion files (:mod:`~gsavatar.motion.amass`) and the one frame-rate resampler
(:mod:`~gsavatar.motion.resample`)."""

from gsavatar.motion.amass import AmassMotion, read_amass
from gsavatar.motion.bvh import BvhMotion, read_bvh
from gsavatar.motion.joint_names import JointMatch, match_joints, read_joint_map
from gsavatar.motion.resample import ResampleTimes, resample_motion, resample_times
from gsavatar.motion.retarget import RetargetedMotion, UndrivenJointsWarning, motion_from_bvh_file, retarget_bvh
from gsavatar.motion.rig_pose import pose_from_local_rotations

__all__ = [
    "AmassMotion",
    "BvhMotion",
    "JointMatch",
    "ResampleTimes",
    "RetargetedMotion",
    "UndrivenJointsWarning",
    "match_joints",
    "motion_from_bvh_file",
    "pose_from_local_rotations",
    "read_amass",
    "read_bvh",
    "read_joint_map",
    "resample_motion",
    "resample_times",
    "retarget_bvh",
]
