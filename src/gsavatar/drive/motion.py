"""Driving input: a motion from a ``motion.npz``, another capture, a BVH file (retargeted onto the avatar's rig,
any convention of joint names, :mod:`gsavatar.motion.joint_names`) or an AMASS-style SMPL-X ``.npz`` (SMPL-X
rigs, :mod:`gsavatar.motion.amass`), resampled to the frame rate the appearance predictor was trained at.

Frame rate (the paper names it an open problem): the predictor sees finite-difference
velocities and accelerations of the last ``N_b`` poses, so a motion played at another
rate than the training captures' feeds it velocities scaled by the rate ratio. We
resample the motion onto the training frame times instead, with the one rotation-aware
resampler of :mod:`gsavatar.motion.resample` (source frames survive exactly, e.g. 60 -> 30 fps).
Frame rates read from files must lie in [MIN_FPS, MAX_FPS] (:mod:`gsavatar.data_schema.limits`):
a ``Frame Time`` of 1e9 s or an ``fps`` of 1e-7 would otherwise ask for ~1e10 output frames.

Errors name the file and field (:class:`~gsavatar.data_schema.SchemaError`) or the
argument (``ValueError``).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from gsavatar.data_schema import Capture, Rig, SchemaError, load_capture
from gsavatar.data_schema.limits import check_fps, check_motion_values, check_resampled_frames, fps_problem
from gsavatar.motion.amass import AMASS_KEYS, UpAxis, is_amass, read_amass
from gsavatar.motion.joint_names import read_joint_map
from gsavatar.motion.resample import resample_motion
from gsavatar.motion.retarget import motion_from_bvh_file
from gsavatar.utils.io import read_npz
from gsavatar.utils.jsonio import read_json

MOTION_KEYS = ("pose", "root_rotation", "root_translation", "face", "fps")
"""Arrays read from a driving ``motion.npz``; any others are never decompressed."""


class GroundTruth(NamedTuple):
    capture: Capture
    """The capture the motion came from (images, masks, cameras)."""
    frames: list[int]
    """Capture frame shown at each driving frame.  # len T"""


class DrivingMotion(NamedTuple):
    pose: np.ndarray
    """Pose parameters, radians, rig order.  # [T, P] float32"""
    root_rotation: np.ndarray
    """Root rotation, axis-angle.  # [T, 3] float32"""
    root_translation: np.ndarray
    """Root translation, metres.  # [T, 3] float32"""
    face: np.ndarray | None
    """Face embedding or None (driver then feeds zeros).  # [T, E] float32"""
    fps: float
    """Frame rate of these arrays (the target rate after resampling)."""
    gt: GroundTruth | None = None
    """Ground truth for metrics: set for capture sources whose frames survive resampling."""
    source: str = ""
    """Where the motion came from (path), for reports."""
    source_fps: float = 0.0
    """Frame rate of the source before resampling."""

    @property
    def num_frames(self) -> int:
        return int(self.pose.shape[0])


# --------------------------------------------------------------------------- validation + loading
def validate_arrays(
    path: Path, arrays: dict[str, np.ndarray | None], pose_dim: int, face_dim: int | None = None
) -> None:
    """Shapes [T,P]/[T,3]/[T,3]/[T,E], T >= 1, all finite, pose and root within +-MAX_MOTION_VALUE, face within
    float32. Raises SchemaError(path, field)."""
    T = None
    for key, width in (("pose", pose_dim), ("root_rotation", 3), ("root_translation", 3), ("face", face_dim)):
        a = arrays.get(key)
        if a is None:
            if key != "face":
                raise SchemaError(path, key, "missing")
            continue
        if a.dtype.kind not in "biuf":
            raise SchemaError(path, key, f"expected an array of real numbers, got dtype {a.dtype}")
        if a.ndim != 2 or (width is not None and a.shape[1] != width):
            raise SchemaError(
                path,
                key,
                f"expected shape [T, {width if width is not None else 'E'}], got {list(a.shape)}"
                + (" (pose width must match the avatar's rig)" if key == "pose" else ""),
            )
        if T is None:
            T = a.shape[0]
        elif a.shape[0] != T:
            raise SchemaError(path, key, f"has {a.shape[0]} frames, pose has {T}")
        bad = ~np.isfinite(a)
        if bad.any():
            f, c = np.argwhere(bad)[0]
            raise SchemaError(path, key, f"{int(bad.sum())} NaN/Inf values (first at frame {f}, column {c})")
        if key != "face":
            check_motion_values(a, path, key)
        elif (np.abs(a.astype(np.float64)) > np.finfo(np.float32).max).any():  # no units, but stored as float32
            raise SchemaError(path, key, "values beyond the float32 range (they would become inf)")
    if not T:
        raise SchemaError(path, "pose", "no frames")


def _npz_fps(path: Path, z: dict[str, np.ndarray], fps: float | None) -> tuple[float, Path, str]:
    """Frame rate of a motion npz and where it came from: (fps, file, field), checked against the
    plausible range (the ``fps`` argument: ValueError; a file: SchemaError naming it)."""
    if fps is not None:
        problem = fps_problem(fps)
        if problem is not None:
            raise ValueError(f"fps (frame rate of {path.name}) must be a plausible frame rate: {problem}")
        return float(fps), path, "fps"
    if "fps" in z:
        a = np.asarray(z["fps"]).reshape(-1)
        if a.size != 1 or a.dtype.kind not in "iuf":
            raise SchemaError(path, "fps", f"expected one number, got {a.size} values of dtype {a.dtype}")
        return check_fps(float(a[0]), path, "fps"), path, "fps"
    for side in (path.with_suffix(".json"), path.parent / "capture.json"):
        if side.exists():
            obj = read_json(side)
            if not isinstance(obj, dict):
                raise SchemaError(side, "", f"expected a JSON object with an 'fps' field, got {type(obj).__name__}")
            v = obj.get("fps")
            if v is not None:
                return check_fps(v, side, "fps"), side, "fps"
    raise ValueError(
        f"{path}: frame rate unknown: pass fps=, store an 'fps' array in the npz, or write "
        f'{path.with_suffix(".json").name} with {{"fps": ...}}'
    )


def _select(n: int, start: int, count: int | None, what: Path) -> slice:
    if not 0 <= start < n:
        raise ValueError(f"start must be in [0, {n}) for {what}, got {start}")
    if count is not None and count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    return slice(start, n if count is None else min(n, start + count))


def _finish(
    pose,
    rr,
    rt,
    face,
    fps_in: float,
    rig: Rig,
    target_fps: float | None,
    source: Path,
    gt_capture: Capture | None = None,
    gt_frames: list[int] | None = None,
    fps_from: tuple[Path, str] | None = None,
) -> DrivingMotion:
    """``fps_from``: (file, field) the source frame rate was read from, named when resampling is refused."""
    fps_out = fps_in if target_fps is None else float(target_fps)
    gt = None
    if abs(fps_out - fps_in) < 1e-9 * fps_in:
        pose, rr, rt = (np.asarray(x, np.float32) for x in (pose, rr, rt))
        face = None if face is None else np.asarray(face, np.float32)
        if gt_capture is not None:
            gt = GroundTruth(gt_capture, list(gt_frames))
    else:
        check_resampled_frames(len(pose), fps_in, fps_out, *(fps_from or (source, "fps")))
        pose, rr, rt, face, t = resample_motion(pose, rr, rt, face, rig, fps_in, fps_out)
        if gt_capture is not None and not t.alpha.any():  # e.g. 60 -> 30: every frame is a source frame
            gt = GroundTruth(gt_capture, [gt_frames[i] for i in t.i0])
    return DrivingMotion(pose, rr, rt, face, fps_out, gt, str(source), float(fps_in))


def load_driving_motion(
    source: str | Path,
    rig: Rig,
    target_fps: float | None = None,
    *,
    fps: float | None = None,
    start: int = 0,
    count: int | None = None,
    split: str | None = None,
    joint_map: str | Path | None = None,
    amass_up: UpAxis = "z",
) -> DrivingMotion:
    """Load a driving motion for an avatar with rig ``rig`` and resample it to ``target_fps``.

    source: a ``motion.npz`` (fps from ``fps``, an ``fps`` array in the npz, a sidecar
        ``<name>.json`` ``{"fps": ..}`` or a ``capture.json`` beside it), a capture directory
        (its ``motion.npz`` + ``capture.json``; ground truth for metrics), or a ``.bvh`` file
        (retargeted onto ``rig`` by :func:`gsavatar.motion.retarget.motion_from_bvh_file`).
    target_fps: the rate the predictor was trained at (None: keep the source rate).
    start, count: source frames ``[start, start + count)`` (BVH: ``count`` output frames).
    split: capture sources only: use this split's frames (must be consecutive), e.g. ``test``.
    joint_map: BVH sources: a JSON file ``{"<rig joint>": "<BVH joint>" | null}`` overriding the name matching
        (:func:`gsavatar.motion.joint_names.read_joint_map`).
    amass_up: AMASS sources (an npz with ``poses`` [F, 165] and ``trans``): the file's up axis (``z``: AMASS's,
        turned to our Y up; ``y``: as it is). Its frame rate: ``mocap_frame_rate``, else as for a motion.npz.
    """
    src = Path(source)
    if not src.exists():
        raise SchemaError(src, "", "driving motion not found (expected a motion.npz, capture directory or .bvh file)")
    if target_fps is not None and fps_problem(target_fps) is not None:
        raise ValueError(f"target_fps must be a plausible frame rate: {fps_problem(target_fps)}")
    if split is not None and not src.is_dir():
        raise ValueError(f"split={split!r} needs a capture directory as source, got {src}")
    if joint_map is not None and src.suffix.lower() != ".bvh":
        raise ValueError(f"joint_map ({joint_map}) applies to BVH motions only, got {src}")
    if src.is_dir():
        if not (src / "capture.json").exists():
            raise SchemaError(src / "capture.json", "", "not a capture directory (capture.json missing)")
        cap = load_capture(src)
        if cap.rig.pose_dim != rig.pose_dim:
            raise SchemaError(
                src / "template" / "rig.json",
                "pose_params",
                f"this capture's pose has {cap.rig.pose_dim} slots, the avatar's rig {rig.pose_dim}",
            )
        frames = list(range(cap.num_frames))
        if split is not None:
            if split not in cap.splits:
                raise ValueError(f"split must be one of {sorted(cap.splits)}, got {split!r}")
            frames = sorted(cap.splits[split].frames)
            if frames != list(range(frames[0], frames[-1] + 1)):
                raise ValueError(f"split {split!r} of {src} is not a run of consecutive frames; use start/count")
        frames = frames[_select(len(frames), start, count, src)]
        fps_in = check_fps(cap.fps, src / "capture.json", "fps")
        m = cap.motion
        face = None if m.face is None else m.face[frames]
        return _finish(
            m.pose[frames],
            m.root_rotation[frames],
            m.root_translation[frames],
            face,
            fps_in,
            rig,
            target_fps,
            src,
            cap,
            frames,
            fps_from=(src / "capture.json", "fps"),
        )
    if src.suffix.lower() == ".bvh":
        names = None if joint_map is None else read_joint_map(joint_map)
        m = motion_from_bvh_file(
            src,
            rig,
            fps_out=target_fps,
            start=start,
            count=count,
            name_map=names,
            name_map_file=joint_map or "name_map",
        )
        validate_arrays(
            src,
            {"pose": m.pose, "root_rotation": m.root_rotation, "root_translation": m.root_translation},
            rig.pose_dim,
        )
        return DrivingMotion(
            m.pose, m.root_rotation, m.root_translation, None, float(m.fps), None, str(src), float(m.fps)
        )
    if src.suffix.lower() == ".npz":
        z = read_npz(src, keys=MOTION_KEYS + AMASS_KEYS)
        if is_amass(z):
            a = read_amass(src, rig, amass_up, z)
            if fps is None and a.fps is not None:  # fps= (--motion-fps) wins over the file's own rate
                fps_in, *fps_from = a.fps, src, a.fps_field
            else:
                fps_in, *fps_from = _npz_fps(src, {}, fps)
            sl = _select(len(a.pose), start, count, src)
            return _finish(
                a.pose[sl],
                a.root_rotation[sl],
                a.root_translation[sl],
                None,
                fps_in,
                rig,
                target_fps,
                src,
                fps_from=tuple(fps_from),
            )
        arrays = {k: z.get(k) for k in MOTION_KEYS if k != "fps"}
        validate_arrays(src, arrays, rig.pose_dim)
        fps_in, *fps_from = _npz_fps(src, z, fps)
        sl = _select(arrays["pose"].shape[0], start, count, src)
        face = None if arrays["face"] is None else arrays["face"][sl]
        return _finish(
            arrays["pose"][sl],
            arrays["root_rotation"][sl],
            arrays["root_translation"][sl],
            face,
            fps_in,
            rig,
            target_fps,
            src,
            fps_from=tuple(fps_from),
        )
    raise ValueError(f"source must be a .npz, .bvh or capture directory, got {src}")
