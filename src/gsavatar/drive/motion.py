"""Driving input: a motion from a ``motion.npz``, another capture, or a BVH file, resampled
to the frame rate the appearance predictor was trained at.

Frame rate (the paper names it an open problem): the predictor sees finite-difference
velocities and accelerations of the last ``N_b`` poses, so a motion played at another
rate than the training captures' feeds it velocities scaled by the rate ratio. We
resample the motion onto the training frame times instead. Output frame ``k`` is at time
``k / fps_out`` from the first source frame (the clip never extends past the last source
frame), so 60 -> 30 fps keeps every other frame *exactly* and 15 -> 30 inserts midpoints.
Interpolation is rotation-aware:

- root rotation (axis-angle) and each joint with a single ``axis_angle`` parameter:
  quaternion slerp (shortest arc), back to a rotation vector;
- each joint with three ``euler`` parameters on principal axes (``rz, ry, rx`` etc.,
  consecutive axes distinct, signs allowed): the joint's local rotation is built from its
  angles (first listed = leftmost factor), slerped, and decomposed back into the same
  sequence; of the two Euler solutions (and their 2π wraps) we keep the one closest to the
  linear interpolation of the angles, so the angle curves stay continuous;
- a joint with one euler parameter (a hinge): linear in the angle, which *is* the slerp
  for steps below π; joints with two euler parameters, mixed kinds or non-principal axes:
  linear per parameter (a slerped rotation generally leaves their 1-2 DOF manifold);
- root translation and face embedding: linear.

Frame rates must lie in [MIN_FPS, MAX_FPS] and a resampled motion may have at most
MAX_RESAMPLED_FRAMES frames (:mod:`gsavatar.data_schema.limits`): a ``Frame Time`` of 1e9 s or an
``fps`` of 1e-7 would otherwise ask for ~1e10 output frames.

Errors name the file and field (:class:`~gsavatar.data_schema.SchemaError`) or the
argument (``ValueError``).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from gsavatar.data_schema import Capture, Rig, SchemaError, load_capture
from gsavatar.data_schema.limits import MAX_RESAMPLED_FRAMES, check_fps, check_resampled_frames, fps_problem
from gsavatar.utils.io import read_npz
from gsavatar.utils.jsonio import read_json

_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}
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


class ResampleTimes(NamedTuple):
    i0: np.ndarray
    """Left source frame of each output frame.  # [T_out] int64"""
    i1: np.ndarray
    """Right source frame.  # [T_out] int64"""
    alpha: np.ndarray
    """Weight of ``i1`` in [0, 1); exactly 0 on source frames.  # [T_out] float64"""


# --------------------------------------------------------------------------- stateless math
def resample_times(n_in: int, fps_in: float, fps_out: float) -> ResampleTimes:
    """Source positions of the output frames ``k / fps_out`` within ``[0, (n_in - 1) / fps_in]``."""
    if n_in < 1:
        raise ValueError(f"n_in must be >= 1, got {n_in}")
    if not (fps_in > 0 and fps_out > 0 and math.isfinite(fps_in) and math.isfinite(fps_out)):
        raise ValueError(f"fps_in and fps_out must be positive, got {fps_in}, {fps_out}")
    ratio = fps_in / fps_out
    n_out = int(math.floor((n_in - 1) / ratio + 1e-6)) + 1
    if n_out > MAX_RESAMPLED_FRAMES:
        raise ValueError(f"resampling {n_in} frames from {fps_in:g} to {fps_out:g} fps makes {n_out} frames, "
                         f"more than the {MAX_RESAMPLED_FRAMES} allowed")
    s = np.arange(n_out, dtype=np.float64) * ratio
    i0 = np.floor(s + 1e-6).astype(np.int64)
    a = s - i0
    a[np.abs(a) < 1e-6] = 0.0
    i0 = np.minimum(i0, n_in - 1)
    a[i0 == n_in - 1] = 0.0
    return ResampleTimes(i0, np.minimum(i0 + 1, n_in - 1), np.clip(a, 0.0, 1.0))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Shortest-arc slerp of unit quaternions (any component order). [...,4], [...,4], [...] -> [...,4]"""
    q1 = np.where((np.sum(q0 * q1, -1) < 0)[..., None], -q1, q1)
    d = np.clip(np.sum(q0 * q1, -1), -1.0, 1.0)
    th = np.arccos(d)
    s = np.sin(th)
    small = s < 1e-8
    s_safe = np.where(small, 1.0, s)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * th) / s_safe)
    w1 = np.where(small, alpha, np.sin(alpha * th) / s_safe)
    q = w0[..., None] * q0 + w1[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def slerp_rotvec(r0: np.ndarray, r1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Slerp between axis-angle rotations. [N,3], [N,3], [N] -> [N,3]"""
    q = quat_slerp(Rotation.from_rotvec(r0).as_quat(), Rotation.from_rotvec(r1).as_quat(), alpha)
    return Rotation.from_quat(q).as_rotvec()


def _wrap_to(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Add multiples of 2π to ``x`` to bring it closest to ``ref`` (elementwise)."""
    return x + 2 * np.pi * np.round((ref - x) / (2 * np.pi))


def euler_from_matrix_near(R: np.ndarray, seq: str, ref: np.ndarray) -> np.ndarray:
    """Intrinsic Euler angles (``R = R_seq[0](a0) R_seq[1](a1) R_seq[2](a2)``) of R [N,3,3],
    choosing among the two solutions and their 2π wraps the one closest to ``ref`` [N,3]. -> [N,3]"""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gimbal lock: any valid split is fine, ref decides the rest
        e = Rotation.from_matrix(R).as_euler(seq)
    alt = e.copy()
    alt[:, 0] += np.pi
    alt[:, 2] += np.pi
    alt[:, 1] = -e[:, 1] if seq[0] == seq[2] else np.pi - e[:, 1]
    cands = np.stack([_wrap_to(e, ref), _wrap_to(alt, ref)])  # [2, N, 3]
    best = np.argmin(((cands - ref[None]) ** 2).sum(-1), axis=0)  # [N]
    return cands[best, np.arange(len(R))]


def _joint_layouts(rig: Rig) -> list[tuple[str, list[int], str, np.ndarray]]:
    """Per joint with parameters: (kind, pose slots, euler seq, axis signs).

    kind: ``aa`` (one axis-angle param), ``euler3`` (three principal-axis euler params,
    consecutive axes distinct), ``linear`` (anything else)."""
    slots: dict[str, list[int]] = {}
    params: dict[str, list] = {}
    k = 0
    for p in rig.params:
        slots.setdefault(p.joint, []).extend(range(k, k + p.size))
        params.setdefault(p.joint, []).append(p)
        k += p.size
    out = []
    for j, ps in params.items():
        if len(ps) == 1 and ps[0].kind == "axis_angle":
            out.append(("aa", slots[j], "", np.ones(3)))
            continue
        if len(ps) == 3 and all(p.kind == "euler" for p in ps):
            letters, signs = [], []
            for p in ps:
                ax = np.asarray(p.axis, dtype=np.float64)
                s = float(np.sign(ax[np.argmax(np.abs(ax))]))
                letter = _AXES.get(tuple(float(round(v, 6)) for v in ax * s))
                letters.append(letter)
                signs.append(s)
            seq = "".join(letter or "?" for letter in letters)
            if "?" not in seq and seq[0] != seq[1] and seq[1] != seq[2]:
                out.append(("euler3", slots[j], seq, np.array(signs)))
                continue
        out.append(("linear", slots[j], "", np.ones(3)))
    return out


def _lerp(x: np.ndarray, t: ResampleTimes) -> np.ndarray:
    a = t.alpha.reshape(-1, *([1] * (x.ndim - 1)))
    return (1.0 - a) * x[t.i0] + a * x[t.i1]


def resample_motion(pose: np.ndarray, root_rotation: np.ndarray, root_translation: np.ndarray,
                    face: np.ndarray | None, rig: Rig, fps_in: float, fps_out: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, ResampleTimes]:
    """Rotation-aware resampling (module docstring). pose [T,P], root_rotation [T,3],
    root_translation [T,3], face [T,E] | None -> the same at ``fps_out`` (float32) + the times.
    Output frames that land on a source frame are copied bit-exactly."""
    pose = np.asarray(pose, np.float64)
    if pose.ndim != 2 or pose.shape[1] != rig.pose_dim:
        raise ValueError(f"pose must be [T, {rig.pose_dim}], got {list(pose.shape)}")
    t = resample_times(pose.shape[0], fps_in, fps_out)
    new_pose = _lerp(pose, t)
    moving = t.alpha > 0
    if moving.any():
        i0, i1, a = t.i0[moving], t.i1[moving], t.alpha[moving]
        for kind, sl, seq, signs in _joint_layouts(rig):
            if kind == "aa":
                new_pose[np.ix_(moving, sl)] = slerp_rotvec(pose[i0][:, sl], pose[i1][:, sl], a)
            elif kind == "euler3":
                e0, e1 = pose[i0][:, sl] * signs, pose[i1][:, sl] * signs
                q = quat_slerp(Rotation.from_euler(seq, e0).as_quat(), Rotation.from_euler(seq, e1).as_quat(), a)
                ref = (1 - a[:, None]) * e0 + a[:, None] * e1
                new_pose[np.ix_(moving, sl)] = euler_from_matrix_near(Rotation.from_quat(q).as_matrix(), seq, ref) * signs
    rr = np.asarray(root_rotation, np.float64)
    new_rr = rr[t.i0].copy()
    if moving.any():
        new_rr[moving] = slerp_rotvec(rr[t.i0[moving]], rr[t.i1[moving]], t.alpha[moving])
    new_rt = _lerp(np.asarray(root_translation, np.float64), t)
    new_face = None if face is None else _lerp(np.asarray(face, np.float64), t)
    # bit-exact copies on source frames
    exact = ~moving
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    out = [f32(new_pose), f32(new_rr), f32(new_rt), None if face is None else f32(new_face)]
    for o, src in zip(out, (pose, rr, root_translation, face)):
        if o is not None:
            o[exact] = np.asarray(src, np.float32)[t.i0[exact]]
    return out[0], out[1], out[2], out[3], t


# --------------------------------------------------------------------------- validation + loading
def validate_arrays(path: Path, arrays: dict[str, np.ndarray | None], pose_dim: int, face_dim: int | None = None) -> None:
    """Shapes [T,P]/[T,3]/[T,3]/[T,E], T >= 1, all finite. Raises SchemaError(path, field)."""
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
            raise SchemaError(path, key, f"expected shape [T, {width if width is not None else 'E'}], got {list(a.shape)}"
                              + (" (pose width must match the avatar's rig)" if key == "pose" else ""))
        if T is None:
            T = a.shape[0]
        elif a.shape[0] != T:
            raise SchemaError(path, key, f"has {a.shape[0]} frames, pose has {T}")
        bad = ~np.isfinite(a)
        if bad.any():
            f, c = np.argwhere(bad)[0]
            raise SchemaError(path, key, f"{int(bad.sum())} NaN/Inf values (first at frame {f}, column {c})")
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
    raise ValueError(f"{path}: frame rate unknown: pass fps=, store an 'fps' array in the npz, or write "
                     f"{path.with_suffix('.json').name} with {{\"fps\": ...}}")


def _select(n: int, start: int, count: int | None, what: Path) -> slice:
    if not 0 <= start < n:
        raise ValueError(f"start must be in [0, {n}) for {what}, got {start}")
    if count is not None and count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    return slice(start, n if count is None else min(n, start + count))


def _finish(pose, rr, rt, face, fps_in: float, rig: Rig, target_fps: float | None, source: Path,
            gt_capture: Capture | None = None, gt_frames: list[int] | None = None,
            fps_from: tuple[Path, str] | None = None) -> DrivingMotion:
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


def load_driving_motion(source: str | Path, rig: Rig, target_fps: float | None = None, *, fps: float | None = None,
                        start: int = 0, count: int | None = None, split: str | None = None) -> DrivingMotion:
    """Load a driving motion for an avatar with rig ``rig`` and resample it to ``target_fps``.

    source: a ``motion.npz`` (fps from ``fps``, an ``fps`` array in the npz, a sidecar
        ``<name>.json`` ``{"fps": ..}`` or a ``capture.json`` beside it), a capture directory
        (its ``motion.npz`` + ``capture.json``; ground truth for metrics), or a ``.bvh`` file
        (retargeted onto ``rig`` by :func:`gsavatar.synth.retarget.motion_from_bvh_file`).
    target_fps: the rate the predictor was trained at (None: keep the source rate).
    start, count: source frames ``[start, start + count)`` (BVH: ``count`` output frames).
    split: capture sources only: use this split's frames (must be consecutive), e.g. ``test``.
    """
    src = Path(source)
    if not src.exists():
        raise SchemaError(src, "", "driving motion not found (expected a motion.npz, capture directory or .bvh file)")
    if target_fps is not None and fps_problem(target_fps) is not None:
        raise ValueError(f"target_fps must be a plausible frame rate: {fps_problem(target_fps)}")
    if split is not None and not src.is_dir():
        raise ValueError(f"split={split!r} needs a capture directory as source, got {src}")
    if src.is_dir():
        if not (src / "capture.json").exists():
            raise SchemaError(src / "capture.json", "", "not a capture directory (capture.json missing)")
        cap = load_capture(src)
        if cap.rig.pose_dim != rig.pose_dim:
            raise SchemaError(src / "template" / "rig.json", "pose_params",
                              f"this capture's pose has {cap.rig.pose_dim} slots, the avatar's rig {rig.pose_dim}")
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
        return _finish(m.pose[frames], m.root_rotation[frames], m.root_translation[frames], face, fps_in, rig,
                       target_fps, src, cap, frames, fps_from=(src / "capture.json", "fps"))
    if src.suffix.lower() == ".bvh":
        from gsavatar.synth.retarget import motion_from_bvh_file

        m = motion_from_bvh_file(src, rig, fps_out=target_fps, start=start, count=count)
        validate_arrays(src, {"pose": m.pose, "root_rotation": m.root_rotation, "root_translation": m.root_translation},
                        rig.pose_dim)
        return DrivingMotion(m.pose, m.root_rotation, m.root_translation, None, float(m.fps), None, str(src), float(m.fps))
    if src.suffix.lower() == ".npz":
        z = read_npz(src, keys=MOTION_KEYS)
        arrays = {k: z.get(k) for k in MOTION_KEYS if k != "fps"}
        validate_arrays(src, arrays, rig.pose_dim)
        fps_in, *fps_from = _npz_fps(src, z, fps)
        sl = _select(arrays["pose"].shape[0], start, count, src)
        face = None if arrays["face"] is None else arrays["face"][sl]
        return _finish(arrays["pose"][sl], arrays["root_rotation"][sl], arrays["root_translation"][sl], face, fps_in,
                       rig, target_fps, src, fps_from=tuple(fps_from))
    raise ValueError(f"source must be a .npz, .bvh or capture directory, got {src}")
