"""Capture format v1: the input contract of ``avatar-prep``.

A capture directory (THuman4.0/AvatarReX-style)::

    capture.json        {"format": "gsavatar-capture", "version": 1, "fps", "num_frames", "units": "m"}
    calibration.json    {cam: {"K": 3x3, "R": 3x3, "T": [3], "distCoeff": [5]?, "imgSize": [w, h]}}
                        world-to-camera, x_cam = R x_world + T, OpenCV axes (+z forward, +y down)
    images/{cam}/{frame:08d}.{png|jpg|exr}
    masks/{cam}/{frame:08d}.png         foreground 0..255
    template/           mesh.obj, rig.json, skin_weights.npz, face_uv_mask.png?
    motion.npz          pose [F,P] rad, root_rotation [F,3] axis-angle, root_translation [F,3] m, face [F,E]?
    splits.json         {"train": {"frames": [...], "cameras": [...]}, "test": {...}}

:func:`load_capture` validates all of it and raises :class:`SchemaError` naming the
file and field. Images are checked lazily per frame (:meth:`Capture.image_path`) and
fully by :func:`check_images`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.data_schema.rig import Rig, load_rig
from gsavatar.data_schema.template import Template, load_template
from gsavatar.data_schema.limits import check_fps, check_motion_values
from gsavatar.utils.io import atomic_save_npz, atomic_write_json, oiio_error, read_npz
from gsavatar.utils.jsonio import is_int, read_json
from gsavatar.utils.paths import check_name

FOCAL_RANGE = (0.01, 100.0)
"""Plausible focal lengths, in multiples of the image's longer side (a 180° lens is ~0.3, a 1000 mm lens ~30)."""
MAX_DISTORTION = 100.0
"""Largest |coefficient| of the OpenCV distortion model accepted."""
MAX_IMAGE_SIDE = 65536
"""Largest image width/height accepted, pixels."""
MAX_TRANSLATION_M = 1e4
"""Largest |T| component accepted, metres."""
MAX_FRAMES = 10_000_000
"""Largest ``num_frames`` accepted."""

CAPTURE_FORMAT = "gsavatar-capture"
CAPTURE_VERSION = 1
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr")


@dataclass
class Camera:
    name: str
    """Camera name (key in calibration.json and folder under images/)."""
    K: np.ndarray
    """Intrinsics, pixels.  # [3, 3] float64"""
    R: np.ndarray
    """Rotation of ``cam_from_world``.  # [3, 3] float64"""
    T: np.ndarray
    """Translation of ``cam_from_world``, metres.  # [3] float64"""
    dist: np.ndarray
    """OpenCV distortion k1, k2, p1, p2, k3 (zeros if absent).  # [5] float64"""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""

    @property
    def cam_from_world(self) -> np.ndarray:
        """4x4 world-to-camera matrix.  # [4, 4]"""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.T
        return M

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world space.  # [3]"""
        return -self.R.T @ self.T

    def to_json(self) -> dict:
        return {
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "T": self.T.tolist(),
            "distCoeff": self.dist.tolist(),
            "imgSize": [int(self.width), int(self.height)],
        }


@dataclass
class Motion:
    pose: np.ndarray
    """Pose parameters, radians, rig order.  # [F, P] float32"""
    root_rotation: np.ndarray
    """Root rotation, axis-angle.  # [F, 3] float32"""
    root_translation: np.ndarray
    """Root translation, metres.  # [F, 3] float32"""
    face: np.ndarray | None = None
    """Face embedding or None.  # [F, E] float32"""

    @property
    def num_frames(self) -> int:
        return int(self.pose.shape[0])

    def save(self, path: str | Path) -> None:
        arrays = {"pose": self.pose, "root_rotation": self.root_rotation, "root_translation": self.root_translation}
        if self.face is not None:
            arrays["face"] = self.face
        atomic_save_npz(path, **{k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()})


@dataclass
class Split:
    frames: list[int]
    cameras: list[str]


@dataclass
class Capture:
    root: Path
    fps: float
    num_frames: int
    cameras: dict[str, Camera]
    rig: Rig
    template: Template
    motion: Motion
    splits: dict[str, Split]
    image_ext: dict[str, str] = field(default_factory=dict)
    """Image file extension per camera (detected from the first frame)."""

    def image_path(self, cam: str, frame: int) -> Path:
        return self.root / "images" / cam / f"{frame:08d}{self.image_ext.get(cam, '.png')}"

    def mask_path(self, cam: str, frame: int) -> Path:
        return self.root / "masks" / cam / f"{frame:08d}.png"


# --------------------------------------------------------------------------- helpers
def _read_json(path: Path):
    return read_json(path)


def _matrix(v, shape: tuple[int, ...] | None, file: Path, fld: str) -> np.ndarray:
    """JSON numbers (never booleans or strings) as float64 of ``shape`` (None: any), finite."""
    flat = np.ravel(np.asarray(v, dtype=object)).tolist() if isinstance(v, (list, tuple)) else [v]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in flat):
        raise SchemaError(
            file, fld, f"expected numbers{'' if shape is None else f' of shape {list(shape)}'}, got {v!r}"[:300]
        )
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise SchemaError(file, fld, f"expected numbers of shape {list(shape)}") from None
    if shape is not None and a.shape != shape:
        raise SchemaError(file, fld, f"expected shape {list(shape)}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise SchemaError(file, fld, "contains NaN/Inf")
    return a


def parse_calibration(obj, file: Path) -> dict[str, Camera]:
    if not isinstance(obj, dict) or not obj:
        raise SchemaError(file, "", "must be a non-empty object {camera_name: {...}}")
    cams: dict[str, Camera] = {}
    for name, c in obj.items():
        check_name(name, file, name, "camera name")
        if not isinstance(c, dict):
            raise SchemaError(file, name, "must be an object with K, R, T, imgSize")
        for key in ("K", "R", "T", "imgSize"):
            if key not in c:
                raise SchemaError(file, f"{name}.{key}", "missing")
        K = _matrix(c["K"], (3, 3), file, f"{name}.K")
        R = _matrix(c["R"], (3, 3), file, f"{name}.R")
        T = _matrix(np.ravel(np.asarray(c["T"], dtype=object)).tolist(), (3,), file, f"{name}.T")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-6 or np.any(K[2, :2] != 0):
            raise SchemaError(
                file, f"{name}.K", f"not a pinhole intrinsic matrix (fx, fy > 0, last row [0,0,1]): {K.tolist()}"
            )
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1) > 1e-4:
            raise SchemaError(
                file,
                f"{name}.R",
                f"not a rotation (det={np.linalg.det(R):.3f}, |R R^T - I|={np.abs(R @ R.T - np.eye(3)).max():.2g})",
            )
        dist = np.zeros(5)
        if c.get("distCoeff") is not None:
            d = _matrix(np.ravel(np.asarray(c["distCoeff"], dtype=object)).tolist(), None, file, f"{name}.distCoeff")
            if d.size not in (4, 5):
                raise SchemaError(
                    file, f"{name}.distCoeff", f"expected 4 or 5 numbers (k1,k2,p1,p2[,k3]), got {d.size}"
                )
            if np.abs(d).max() > MAX_DISTORTION:
                raise SchemaError(
                    file, f"{name}.distCoeff", f"implausible coefficients {d.tolist()} (|k| > {MAX_DISTORTION:g})"
                )
            dist[: d.size] = d
        size = c["imgSize"]
        if not (
            isinstance(size, (list, tuple))
            and len(size) == 2
            and all(is_int(s) and 0 < s <= MAX_IMAGE_SIDE for s in size)
        ):
            raise SchemaError(
                file, f"{name}.imgSize", f"expected [width, height], integers in [1, {MAX_IMAGE_SIDE}], got {size!r}"
            )
        w, h = int(size[0]), int(size[1])
        side = max(w, h)
        for i, ax in ((0, "fx"), (1, "fy")):
            if not FOCAL_RANGE[0] * side <= K[i, i] <= FOCAL_RANGE[1] * side:
                raise SchemaError(
                    file,
                    f"{name}.K",
                    f"{ax} = {K[i, i]:g} px is implausible for a {w}x{h} image "
                    f"(expected {FOCAL_RANGE[0]:g}-{FOCAL_RANGE[1]:g} x {side} px)",
                )
        if not (-w <= K[0, 2] <= 2 * w and -h <= K[1, 2] <= 2 * h) or abs(K[0, 1]) > K[0, 0]:
            raise SchemaError(
                file,
                f"{name}.K",
                f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) or skew {K[0, 1]:g} implausible for a {w}x{h} image",
            )
        if np.abs(T).max() > MAX_TRANSLATION_M:
            raise SchemaError(file, f"{name}.T", f"{T.tolist()}: more than {MAX_TRANSLATION_M:g} m (units are metres)")
        cams[name] = Camera(name, K, R, T, dist, w, h)
    return cams


def _real_array(a: np.ndarray, file: Path, fld: str) -> np.ndarray:
    """``a`` as float32; SchemaError naming the field unless it holds real numbers (ints, floats, bools)."""
    if a.dtype.kind not in "biuf":
        raise SchemaError(file, fld, f"expected an array of real numbers, got dtype {a.dtype}")
    return a.astype(np.float32)


def load_motion(path: Path, num_frames: int, pose_dim: int, frames_from: Path | None = None) -> Motion:
    """``frames_from``: the file ``num_frames`` comes from (capture.json), named when the frame counts disagree."""
    z = read_npz(path, keys=("pose", "root_rotation", "root_translation", "face"))
    arrays = {}
    for key, width in (("pose", pose_dim), ("root_rotation", 3), ("root_translation", 3)):
        if key not in z:
            raise SchemaError(path, key, f"missing; has {sorted(z)}")
        a = z[key]
        if a.ndim == 2 and a.shape[1] == width and a.shape[0] != num_frames and frames_from is not None:
            raise SchemaError(
                frames_from, "num_frames", f"says {num_frames} frames, but {path.name} {key} has {a.shape[0]}"
            )
        if a.ndim != 2 or a.shape != (num_frames, width):
            raise SchemaError(path, key, f"expected shape [{num_frames}, {width}], got {list(a.shape)}")
        arrays[key] = _real_array(a, path, key)
    face = None
    if "face" in z:
        face = z["face"]
        if face.ndim != 2 or face.shape[0] != num_frames:
            raise SchemaError(path, "face", f"expected shape [{num_frames}, E], got {list(face.shape)}")
        face = arrays["face"] = _real_array(face, path, "face")
    for key, a in arrays.items():
        bad = ~np.isfinite(a)
        if bad.any():
            f, c = np.argwhere(bad)[0]
            raise SchemaError(path, key, f"{int(bad.sum())} NaN/Inf values (first at frame {f}, column {c})")
        if key != "face":  # radians and metres (face embeddings have no units)
            check_motion_values(a, path, key)
    return Motion(arrays["pose"], arrays["root_rotation"], arrays["root_translation"], face)


def parse_splits(obj, file: Path, num_frames: int, cameras: dict[str, Camera]) -> dict[str, Split]:
    if not isinstance(obj, dict) or "train" not in obj:
        raise SchemaError(file, "train", "missing")
    out: dict[str, Split] = {}
    for name, s in obj.items():
        check_name(name, file, name, "split name")
        if not isinstance(s, dict) or "frames" not in s or "cameras" not in s:
            raise SchemaError(file, name, "needs 'frames' and 'cameras'")
        frames = s["frames"]
        if not isinstance(frames, list) or not all(is_int(f) for f in frames):
            raise SchemaError(file, f"{name}.frames", "must be a list of integer frame indices (not booleans)")
        if len(set(frames)) != len(frames):
            raise SchemaError(
                file, f"{name}.frames", f"frame {next(f for f in frames if frames.count(f) > 1)} listed twice"
            )
        if not frames:
            raise SchemaError(file, f"{name}.frames", "empty")
        bad = [f for f in frames if not 0 <= f < num_frames]
        if bad:
            raise SchemaError(file, f"{name}.frames", f"frame {bad[0]} outside [0, {num_frames})")
        cams = s["cameras"]
        if not isinstance(cams, list) or not cams:
            raise SchemaError(file, f"{name}.cameras", "must be a non-empty list of camera names")
        unknown = [c for c in cams if not isinstance(c, str) or c not in cameras]
        if unknown:
            raise SchemaError(file, f"{name}.cameras", f"unknown camera {unknown[0]!r} (not in calibration.json)")
        if len(set(cams)) != len(cams):
            raise SchemaError(
                file, f"{name}.cameras", f"camera {next(c for c in cams if cams.count(c) > 1)!r} listed twice"
            )
        out[name] = Split(list(frames), list(cams))
    # Held-out metrics are only held out if nothing of them was trained on.
    train = out["train"]
    for name, sp in out.items():
        if name == "train":
            continue
        both = sorted(set(sp.cameras) & set(train.cameras))
        if both:
            raise SchemaError(
                file, f"{name}.cameras", f"camera {both[0]!r} is also in train.cameras: splits must not share cameras"
            )
        shared = sorted(set(sp.frames) & set(train.frames))
        if shared:
            raise SchemaError(
                file,
                f"{name}.frames",
                f"frame {shared[0]} is also in train.frames ({len(shared)} shared): splits must not share frames",
            )
    return out


def _detect_ext(root: Path, cam: str) -> str:
    d = root / "images" / cam
    if not d.is_dir():
        raise SchemaError(d, "", f"image folder of camera {cam!r} not found")
    for ext in IMAGE_EXTS:
        if (d / f"{0:08d}{ext}").exists():
            return ext
    for p in sorted(d.iterdir()):
        if p.suffix.lower() in IMAGE_EXTS:
            return p.suffix.lower()
    raise SchemaError(d, "", f"no images ({'/'.join(IMAGE_EXTS)}) for camera {cam!r}")


def load_capture(root: str | Path, check_files: bool = True) -> Capture:
    """Load and validate a capture directory. Raises SchemaError naming file and field."""
    root = Path(root)
    if not root.is_dir():
        raise SchemaError(root, "", "capture directory not found")
    info_path = root / "capture.json"
    info = _read_json(info_path)
    if not isinstance(info, dict):
        raise SchemaError(info_path, "", "must be an object")
    if info.get("format") != CAPTURE_FORMAT:
        raise SchemaError(info_path, "format", f"expected {CAPTURE_FORMAT!r}, got {info.get('format')!r}")
    if info.get("version") != CAPTURE_VERSION:
        raise SchemaError(
            info_path, "version", f"unsupported version {info.get('version')!r}; this gsavatar reads {CAPTURE_VERSION}"
        )
    fps = check_fps(info.get("fps"), info_path, "fps")
    nf = info.get("num_frames")
    if not is_int(nf) or not 0 < nf <= MAX_FRAMES:
        raise SchemaError(info_path, "num_frames", f"must be an integer in [1, {MAX_FRAMES}], got {nf!r}")
    if info.get("units", "m") != "m":
        raise SchemaError(info_path, "units", f"only metres ('m') are supported, got {info.get('units')!r}")
    cal_path = root / "calibration.json"
    cameras = parse_calibration(_read_json(cal_path), cal_path)
    rig = load_rig(root / "template" / "rig.json")
    template = load_template(root / "template", rig.num_joints)
    motion = load_motion(root / "motion.npz", nf, rig.pose_dim, frames_from=info_path)
    splits = parse_splits(_read_json(root / "splits.json"), root / "splits.json", nf, cameras)
    cap = Capture(root, float(fps), nf, cameras, rig, template, motion, splits)
    if check_files:
        for cam in cameras:
            cap.image_ext[cam] = _detect_ext(root, cam)
    return cap


def check_images(cap: Capture, frames: list[int] | None = None, cams: list[str] | None = None) -> None:
    """Verify every image/mask exists and has the calibrated size (reads headers only)."""
    import OpenImageIO as oiio

    frames = list(range(cap.num_frames)) if frames is None else frames
    for cam in cams or list(cap.cameras):
        c = cap.cameras[cam]
        for f in frames:
            for p in (cap.image_path(cam, f), cap.mask_path(cam, f)):
                if not p.exists():
                    raise SchemaError(
                        p, "", f"missing ({'mask' if 'masks' in p.parts else 'image'} of camera {cam!r}, frame {f})"
                    )
                if not p.is_file():  # a FIFO would block the reader forever
                    raise SchemaError(p, "", "not a regular file")
                inp = oiio.ImageInput.open(str(p))
                if inp is None:
                    raise SchemaError(p, "", f"cannot open image: {oiio_error(oiio.geterror)}")
                spec = inp.spec()
                inp.close()
                w, h = spec.width, spec.height
                if spec.get_int_attribute("Orientation", 1) in (5, 6, 7, 8):  # EXIF: shown rotated by 90 degrees
                    w, h = h, w  # read_image applies the orientation, so the upright size must match
                if (w, h) != (c.width, c.height):
                    raise SchemaError(p, "size", f"is {w}x{h}, calibration.json says {c.width}x{c.height} for {cam!r}")


def write_capture_metadata(
    root: str | Path, fps: float, num_frames: int, cameras: dict[str, Camera], splits: dict[str, Split]
) -> None:
    """Write capture.json, calibration.json and splits.json atomically."""
    root = Path(root)
    atomic_write_json(
        root / "capture.json",
        {
            "format": CAPTURE_FORMAT,
            "version": CAPTURE_VERSION,
            "fps": float(fps),
            "num_frames": int(num_frames),
            "units": "m",
        },
    )
    atomic_write_json(root / "calibration.json", {n: c.to_json() for n, c in cameras.items()})
    atomic_write_json(
        root / "splits.json",
        {k: {"frames": list(map(int, s.frames)), "cameras": list(s.cameras)} for k, s in splits.items()},
    )
