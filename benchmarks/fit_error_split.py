"""Which part of a body fit's error costs the avatar: its slow part or its frame-to-frame jitter?

Given a synthetic capture (true poses) and a capture ``avatar-prep fit-body`` made from it, writes captures whose
motion is the true one plus a temporally filtered part of the fit's error, trains the same avatar on each and
reports held-out PSNR inside the mask against the true poses (an oracle decomposition: the product never knows
the truth):

- ``control``: the true motion in the fitted capture's folder (the control: zero error, everything else the fitted
  capture's);
- ``low``: true + Gaussian low-pass of the error (sigma frames): the slow error alone;
- ``high``: true + the rest of the error: the jitter alone;
- ``filtered``: the fitted motion itself low-passed (what a post-fit smoother could do without the truth; it
  smooths the true motion as much as the error);
- ``savgol``: the fitted motion through a Savitzky-Golay filter (local cubic over ``--savgol-window`` frames: keeps
  a cubic motion exactly, so it smooths fast limbs less than the Gaussian).

The error is split in rotation space, not in Euler angles (a fit may name a rotation by the other Euler branch, and
a filtered jump between branches would be an error the fit did not make): per joint the rotation vector of
``L_fit L_true^T`` (joint-local rotations) is filtered, applied to the true rotation and written back as the Euler
angles nearest the true ones; the root rotation likewise, the root translation linearly. ``filtered`` / ``savgol``
smooth the fitted Euler angles themselves and the root rotation as sign-aligned quaternions.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fit_error_split.py --capture out/demo/capture \
        --fitted out/fit_bench_prior_s0/fitted --work out/fit_split_s0 --true-dataset out/demo/dataset \
        [--sigma 2] [--json docs/benchmarks/fit_error_split.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

VARIANTS = ("control", "low", "high", "filtered", "savgol")


def lowpass(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass over frames (axis 0, edges reflected). [F, ...] -> [F, ...]"""
    return gaussian_filter1d(np.asarray(x, np.float64), sigma, axis=0, mode="nearest")


def savgol(x: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay filter over frames (local cubic, polynomial fit at the edges). [F, ...] -> [F, ...]"""
    from scipy.signal import savgol_filter

    return savgol_filter(np.asarray(x, np.float64), window, 3, axis=0, mode="interp")


def smooth_rotations(aa: np.ndarray, sigma: float, filt=None) -> np.ndarray:
    """Low-pass of axis-angle rotations via sign-aligned quaternions (``filt``: another filter of [F, 4]
    arrays instead of the Gaussian). [F, 3] -> [F, 3]"""
    q = Rotation.from_rotvec(aa).as_quat()  # [F, 4]
    for t in range(1, len(q)):  # continuous sign
        if q[t] @ q[t - 1] < 0:
            q[t] = -q[t]
    return Rotation.from_quat(lowpass(q, sigma) if filt is None else filt(q)).as_rotvec()  # from_quat normalises


def split_pose(rig, true_pose: np.ndarray, fit_pose: np.ndarray, part) -> np.ndarray:
    """True pose with ``part`` of the fit's joint-local rotation error (module docstring). -> [F, P]"""
    from gsavatar.geometry.lbs import pose_to_local_rotations
    from gsavatar.motion.rig_pose import pose_near_local_rotations

    L = lambda p: pose_to_local_rotations(torch.as_tensor(p, dtype=torch.float64), rig).numpy()  # noqa: E731
    Lt, Lf = L(true_pose), L(fit_pose)  # [F, J, 3, 3]
    F, J = Lt.shape[:2]
    e = Rotation.from_matrix((Lf @ Lt.transpose(0, 1, 3, 2)).reshape(-1, 3, 3)).as_rotvec().reshape(F, J, 3)
    Ln = Rotation.from_rotvec(part(e).reshape(-1, 3)).as_matrix().reshape(F, J, 3, 3) @ Lt
    return pose_near_local_rotations(Ln, Lt, rig)  # the Euler branch nearest the truth's


def variant_motion(true, fit, name: str, sigma: float, window: int = 9, rig=None):
    """The motion of one variant (module docstring)."""
    from gsavatar.data_schema.capture import Motion

    if name == "control":
        return Motion(true.pose, true.root_rotation, true.root_translation, fit.face)
    if name == "savgol":
        f = lambda x: savgol(x, window)  # noqa: E731
        return Motion(f(fit.pose), smooth_rotations(fit.root_rotation, sigma, f), f(fit.root_translation), fit.face)
    if name == "filtered":
        return Motion(
            lowpass(fit.pose, sigma),
            smooth_rotations(fit.root_rotation, sigma),
            lowpass(fit.root_translation, sigma),
            fit.face,
        )
    e_trans = fit.root_translation - true.root_translation
    R_true = Rotation.from_rotvec(true.root_rotation)
    e_rot = (Rotation.from_rotvec(fit.root_rotation) * R_true.inv()).as_rotvec()  # R_fit R_true^T
    part = (lambda e: lowpass(e, sigma)) if name == "low" else (lambda e: e - lowpass(e, sigma))
    return Motion(
        split_pose(rig, true.pose, fit.pose, part),
        (Rotation.from_rotvec(part(e_rot)) * R_true).as_rotvec(),
        true.root_translation + part(e_trans),
        fit.face,
    )


def write_variant(fitted: Path, out: Path, motion) -> None:
    """A capture linking everything of ``fitted`` but its motion."""
    out.mkdir(parents=True, exist_ok=True)
    for p in fitted.iterdir():
        if p.name in ("motion.npz", "fit"):
            continue
        dst = out / p.name
        if not dst.exists():
            dst.symlink_to(p.resolve(), target_is_directory=p.is_dir())
    motion.save(out / "motion.npz")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True, help="the synthetic capture (true poses)")
    ap.add_argument("--fitted", type=Path, required=True, help="fit-body's output capture of --capture")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--sigma", type=float, default=2.0, help="Gaussian low-pass sigma, frames")
    ap.add_argument("--savgol-window", type=int, default=9, help="Savitzky-Golay window, frames (odd)")
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--true-dataset", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    sys.path.insert(0, str(Path(__file__).parent))
    from fit_body import errors, train_compare  # noqa: E402

    from gsavatar.data_schema import load_capture
    from gsavatar.fitting.keypoints import load_joint_map

    cap, fit = load_capture(a.capture), load_capture(a.fitted)
    jm = load_joint_map("body25", cap.rig, None, template=cap.template)
    res = {
        "command": "PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fit_error_split.py "
        + " ".join(sys.argv[1:]),
        "machine": f"{platform.system()} {platform.machine()}, CPU only, torch {torch.__version__}",
        "sigma_frames": a.sigma,
        "savgol_window": a.savgol_window,
        "fitted": {"errors": errors(cap, fit, jm)},
        "variants": {},
    }
    for name in a.variants:
        d = a.work / name
        write_variant(a.fitted, d, variant_motion(cap.motion, fit.motion, name, a.sigma, a.savgol_window, cap.rig))
        t0 = time.perf_counter()
        tr = train_compare(a.capture, d, a.work, a.true_dataset, a.preset)
        res["variants"][name] = {
            "errors": {k: v for k, v in errors(cap, load_capture(d), jm).items() if not isinstance(v, (dict, list))},
            "train": tr,
            "seconds": round(time.perf_counter() - t0, 1),
        }
        print(name, json.dumps(res["variants"][name]["errors"]), round(tr["psnr_fg_difference_db"], 3), flush=True)
        if a.json:
            a.json.parent.mkdir(parents=True, exist_ok=True)
            a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
