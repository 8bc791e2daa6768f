"""The centre of the body fit's pose prior, from motion capture of the same rig.

The fit's pose prior ``lambda_pose |theta_t - mu|^2`` (:func:`gsavatar.fitting.fit.fit_sequence`) decides every
pose parameter the keypoints do not: the twist of a limb about its bone, the fingers, and, on rigs with
pass-through joints (the CMU skeleton's ``LHipJoint``/``RHipJoint``/``LowerBack``), how a torso rotation is split
between the root and those joints. With ``mu = 0`` (the rest pose) that split is wrong wherever real motion keeps
such joints away from rest; the mean pose of any mocap retargeted onto the same rig carries the right offsets
(docs/fit_body.md measures it). The same motion's per-parameter spread scales the prior
(``lambda_pose sum_p ((theta_p - mu_p) / s_p)^2``, ``s_p^2 = std_p^2 + floor^2``): a degree of freedom real motion
hardly uses (a CMU elbow's abduction and twist, a finger's spread) is held near its mean, so the keypoints' ambiguity
between, say, an upper-arm twist and an elbow abduction is resolved the way bodies move.

Sources: BVH files (retargeted onto the capture's rig with :func:`gsavatar.motion.retarget.motion_from_bvh_file`
at 30 fps) or ``.npz`` files with ``pose`` [F, P] in the rig's parameter order (a capture's ``motion.npz``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_npz


def _poses_of(path: Path, rig) -> np.ndarray:
    """One source's pose parameters [F, P] on ``rig``."""
    if not path.is_file():
        raise SchemaError(path, "", "pose prior file not found")
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        from gsavatar.motion.retarget import motion_from_bvh_file

        with warnings.catch_warnings():  # undriven joints keep their rest rotation: that is the prior we want there
            warnings.simplefilter("ignore")
            try:
                pose = np.asarray(motion_from_bvh_file(path, rig, fps_out=30.0).pose, np.float64)
            except (ValueError, KeyError, IndexError) as e:
                raise SchemaError(path, "", f"could not be read and retargeted onto the capture's rig: {e}") from None
    elif suffix == ".npz":
        z = read_npz(path)
        if "pose" not in z:
            raise SchemaError(path, "pose", "missing (a pose prior .npz holds pose [F, P], like a motion.npz)")
        pose = np.asarray(z["pose"], np.float64)
        if pose.ndim != 2 or pose.shape[1] != rig.pose_dim:
            raise SchemaError(
                path, "pose", f"has shape {list(pose.shape)}; the capture's rig needs [F, {rig.pose_dim}]"
            )
    else:
        raise SchemaError(path, "", f"a pose prior is a .bvh or .npz file, not {suffix or 'a file without suffix'}")
    if len(pose) == 0:
        raise SchemaError(path, "pose", "has no frames")
    if not np.all(np.isfinite(pose)):
        raise SchemaError(path, "pose", "holds NaN or infinite values")
    return pose


def canonical_poses(poses: np.ndarray, rig) -> np.ndarray:
    """The same rotations in one Euler branch: every frame's angles nearest those of the joints' mean rotation.

    Three Euler angles name every rotation twice (``(a, b, c)`` and ``(a + pi, pi - b, c + pi)``, plus 2 pi shifts),
    and a motion made continuous over time (retargeting) wanders from one branch to the other through near-gimbal
    frames: averaging its angles then mixes branches, a mean of nothing. Here each joint's mean rotation (the
    chordal mean: the rotation nearest the sum of the frames' matrices) is expressed in the principal branch and every
    frame takes the branch and shift nearest it. poses [F, P] -> [F, P] float64 (the same local rotations)
    """
    import torch

    from gsavatar.geometry.lbs import pose_to_local_rotations
    from gsavatar.motion.rig_pose import pose_near_local_rotations

    L = pose_to_local_rotations(torch.as_tensor(poses, dtype=torch.float64), rig).numpy()  # [F, J, 3, 3]
    U, _, Vt = np.linalg.svd(L.sum(0))
    D = np.ones(U.shape[:-1])
    D[:, -1] = np.sign(np.linalg.det(U @ Vt))
    M = (U * D[:, None, :]) @ Vt  # [J, 3, 3] chordal mean of each joint
    return pose_near_local_rotations(L, M, rig)  # the mean's own angles: the principal branch


def pose_prior_stats(paths, rig) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mean and standard deviation of every pose parameter over all frames of the ``paths`` (BVH or npz) on ``rig``,
    the angles in one branch (:func:`canonical_poses`). -> (mean [P] float64, std [P] float64, report entry)"""
    poses = [_poses_of(Path(p), rig) for p in paths]
    if not poses:
        raise ValueError("pose_prior_stats needs at least one file")
    allp = canonical_poses(np.concatenate(poses), rig)
    return allp.mean(0), allp.std(0), {"files": [str(p) for p in paths], "frames": int(len(allp))}


def pose_prior_mean(paths, rig) -> tuple[np.ndarray, dict]:
    """The mean pose of every frame of the ``paths`` (BVH or npz) on ``rig``. -> (mean [P] float64, report entry)"""
    mean, _, entry = pose_prior_stats(paths, rig)
    return mean, entry
