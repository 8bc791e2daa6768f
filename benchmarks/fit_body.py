"""``avatar-prep fit-body`` on a synthetic capture whose true poses are known: accuracy, speed, scaling,
and (``--train``) whether the fitted poses train as good an avatar as the true ones.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fit_body.py --capture out/demo/capture \
        --work out/fit_bench [--train] [--json docs/benchmarks/fit_body.json]

Keypoints: the true joints projected with 2 px noise, 10% of the detections moved to random spots (a
detector's confident mistakes), 20% dropped (:func:`gsavatar.fitting.synthetic.synthetic_keypoints`),
written as OpenPose BODY_25 files; then the command itself. Errors: MPJPE over the joints the keypoints
stand for and over all rig joints (fingers, toes and spine joints no keypoint sees included), the root's
geodesic rotation error, and the local rotations' geodesic error of the joints whose child is observed.
Scaling: the fit alone (no files) on the first ``F`` frames with the first ``C`` cameras.
``--train``: ``avatar-prep all`` + ``avatar-train avatar --preset tiny`` on the true and on the fitted
capture, held-out PSNR of each (``avatar-train eval``).
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch


def geodesic(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rotations given as matrices [..., 3, 3] -> [...] radians."""
    tr = np.einsum("...ij,...ij->...", a, b)  # trace(a^T b)
    return np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0))


def errors(cap, fitted, jm) -> dict:
    from gsavatar.geometry.lbs import pose_to_local_rotations, skinning_transforms
    from gsavatar.geometry.rotations import axis_angle_to_matrix

    d = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    m0, m1 = cap.motion, fitted.motion
    T0 = skinning_transforms(cap.rig, d(m0.pose), d(m0.root_rotation), d(m0.root_translation)).numpy()
    T1 = skinning_transforms(cap.rig, d(m1.pose), d(m1.root_rotation), d(m1.root_translation)).numpy()
    h = cap.rig.heads().astype(np.float64)
    J0 = np.einsum("fjab,jb->fja", T0[..., :3, :3], h) + T0[..., :3, 3]
    J1 = np.einsum("fjab,jb->fja", T1[..., :3, :3], h) + T1[..., :3, 3]
    e = 1000 * np.linalg.norm(J1 - J0, axis=-1)
    L0 = pose_to_local_rotations(d(m0.pose), cap.rig).numpy()
    L1 = pose_to_local_rotations(d(m1.pose), cap.rig).numpy()
    parents = cap.rig.parents()
    seen = set(int(j) for j in jm.joints)
    constrained = sorted({int(parents[j]) for j in seen if parents[j] >= 0})  # a joint whose child is observed
    root = geodesic(
        axis_angle_to_matrix(d(m0.root_rotation)).numpy(), axis_angle_to_matrix(d(m1.root_rotation)).numpy()
    )
    local = geodesic(L0[:, constrained], L1[:, constrained])
    # the posed surface (what the avatar sees): template vertices skinned by both motions, every 5th frame
    from gsavatar.geometry.lbs import lbs

    t = cap.template
    sub = slice(None, None, 5)
    V = d(t.vertices)
    si, sw = torch.as_tensor(t.skin_indices).long(), d(t.skin_weights)
    V0 = lbs(V, si, sw, d(T0[sub])).numpy()
    V1 = lbs(V, si, sw, d(T1[sub])).numpy()
    ev = 1000 * np.linalg.norm(V1 - V0, axis=-1)
    dominant = si.numpy()[np.arange(len(si)), sw.numpy().argmax(1)]  # each vertex's region: its main joint
    by_joint = {
        cap.rig.joints[j].name: round(float(ev[:, dominant == j].mean()), 1)
        for j in np.unique(dominant)
        if (dominant == j).sum() >= 20
    }
    return {
        "vertex_error_by_joint_mm": dict(sorted(by_joint.items(), key=lambda kv: -kv[1])),
        "vertex_error_mm": float(ev.mean()),
        "vertex_error_p95_mm": float(np.percentile(ev, 95)),
        "mpjpe_mapped_mm": float(e[:, jm.joints].mean()),
        "mpjpe_mapped_p95_mm": float(np.percentile(e[:, jm.joints], 95)),
        "mpjpe_all_mm": float(e.mean()),
        # jitter: the mean joint acceleration (second difference over frames) of the fitted and the true motion
        "joint_acceleration_mm": float(1000 * np.linalg.norm(J1[2:] - 2 * J1[1:-1] + J1[:-2], axis=-1).mean()),
        "true_joint_acceleration_mm": float(1000 * np.linalg.norm(J0[2:] - 2 * J0[1:-1] + J0[:-2], axis=-1).mean()),
        "root_rotation_deg": float(np.degrees(root).mean()),
        "root_translation_mm": float(1000 * np.linalg.norm(m1.root_translation - m0.root_translation, axis=-1).mean()),
        "local_rotation_deg": float(np.degrees(local).mean()),
        "local_rotation_joints": [cap.rig.joints[j].name for j in constrained],
        "note": "local rotations include the twist about the bone, which joint positions do not determine",
    }


def scaling(cap, jm, frames: list[int], views: list[int], seed: int = 0) -> list[dict]:
    """Fit time and error on the first F frames with the first C views (``fit_sequence`` with the default
    FitConfig and rest-pose prior: ``--fit-args`` do not apply here)."""
    from gsavatar.fitting.fit import FitConfig, fit_sequence, posed_keypoints
    from gsavatar.fitting.synthetic import synthetic_keypoints
    from gsavatar.fitting.triangulate import triangulate
    from gsavatar.synth.render import pose_joint_positions

    names = sorted(cap.cameras)
    m = cap.motion
    J = pose_joint_positions(cap.rig, m.pose, m.root_rotation, m.root_translation)
    P = posed_keypoints(cap.rig, jm, m.pose, m.root_rotation, m.root_translation)
    rows = []
    for C in views:
        cams = [cap.cameras[n] for n in names[:C]]
        for F in frames:
            kp = synthetic_keypoints(P[:F], cams, jm, seed=seed)
            t0 = time.perf_counter()
            tri = triangulate(kp, cams)
            t1 = time.perf_counter()
            res = fit_sequence(cap.rig, cams, kp, jm, tri.points, tri.inliers, FitConfig())
            t2 = time.perf_counter()
            Jf = pose_joint_positions(cap.rig, res["pose"], res["root_rotation"], res["root_translation"])
            err = float(1000 * np.linalg.norm(Jf[:, jm.joints] - J[:F, jm.joints], axis=-1).mean())
            rows.append(
                {
                    "views": C,
                    "frames": F,
                    "triangulation_s": round(t1 - t0, 3),
                    "fit_s": round(t2 - t1, 2),
                    "fit_s_per_frame": round((t2 - t1) / F, 4),
                    "mpjpe_mapped_mm": round(err, 2),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def train_compare(
    true_cap: Path, fitted_cap: Path, work: Path, true_dataset: Path | None = None, preset: str = "tiny"
) -> dict:
    from gsavatar.prep.cli import main as prep
    from gsavatar.train.cli import main as train

    out = {}
    for name, cap in (("true_poses", true_cap), ("fitted_poses", fitted_cap)):
        tag = name if name == "true_poses" or fitted_cap.name == "fitted" else f"{fitted_cap.name}_poses"
        ds, run = work / f"dataset_{tag}", work / f"run_{tag}_{preset}"
        if name == "true_poses" and true_dataset is not None:
            ds = true_dataset  # prepared before from the same capture: `all` below only checks it
        if prep(["all", "--capture", str(cap), "--out", str(ds)]) != 0:
            raise SystemExit(f"avatar-prep all failed on {cap}")
        t0 = time.perf_counter()
        if train(["avatar", "--dataset", str(ds), "--out", str(run), "--preset", preset]) != 0:
            raise SystemExit(f"avatar-train failed on {ds}")
        m = json.loads((run / "eval" / "metrics.json").read_text())
        out[name] = {k: m["test_frames_heldout_cams"][k] for k in ("psnr", "psnr_fg", "ssim")} | {
            "train_psnr_fg": m["train_frames_heldout_cams"]["psnr_fg"],
            "seconds": round(time.perf_counter() - t0, 1),
        }
    out["psnr_fg_difference_db"] = out["fitted_poses"]["psnr_fg"] - out["true_poses"]["psnr_fg"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True, help="scratch folder (keypoints, fitted capture, runs)")
    ap.add_argument("--frames", type=int, nargs="+", default=[30, 60, 120])
    ap.add_argument("--views", type=int, nargs="+", default=[4, 8, 12])
    ap.add_argument("--format", choices=["body25", "coco_wholebody"], default="body25")
    ap.add_argument("--train", action="store_true", help="also train tiny avatars on the true and the fitted poses")
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--true-dataset", type=Path, default=None, help="an existing dataset prepared from --capture")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--fit-args", default="", help="extra fit-body flags, e.g. '--fit.w-silhouette 1'")
    ap.add_argument("--fitted-name", default="fitted", help="folder of the fitted capture under --work")
    ap.add_argument("--preset", default="tiny", help="avatar-train preset of --train's two avatars")
    ap.add_argument("--seed", type=int, default=0, help="seed of the keypoints' noise, outliers and drops")
    ap.add_argument(
        "--joint-map",
        type=Path,
        default=None,
        help="a keypoint -> joint map file or packaged map name, e.g. body25_hands (keypoints and fit)",
    )
    a = ap.parse_args()

    from gsavatar.data_schema import load_capture
    from gsavatar.fitting.fit import posed_keypoints
    from gsavatar.fitting.keypoints import load_joint_map
    from gsavatar.fitting.synthetic import synthetic_keypoints, write_coco_wholebody, write_openpose
    from gsavatar.prep.cli import main as prep

    cap = load_capture(a.capture)
    jm = load_joint_map(a.format, cap.rig, a.joint_map, template=cap.template)
    names = sorted(cap.cameras)
    m = cap.motion
    kdir, fitted = a.work / "keypoints", a.work / a.fitted_name
    # the keypoints are made once per work folder: what made them is recorded, and another seed / format / map
    # asks for another folder instead of silently fitting the old ones
    made = {"seed": a.seed, "format": a.format, "keypoints": [int(k) for k in jm.keypoints], "names": list(jm.names)}
    if not kdir.exists():
        P = posed_keypoints(cap.rig, jm, m.pose, m.root_rotation, m.root_translation)
        write = write_openpose if a.format == "body25" else write_coco_wholebody
        kp = synthetic_keypoints(P, [cap.cameras[n] for n in names], jm, seed=a.seed)
        write(kdir, kp, names, list(range(cap.num_frames)))
        (a.work / "keypoints.json").write_text(json.dumps(made))
    elif not (a.work / "keypoints.json").exists() or json.loads((a.work / "keypoints.json").read_text()) != made:
        raise SystemExit(f"{kdir} holds keypoints of another seed, format or joint map: use another --work")
    t0 = time.perf_counter()
    cmd = [
        "fit-body",
        "--capture",
        str(a.capture),
        "--keypoints",
        str(kdir),
        "--out",
        str(fitted),
        *(["--joint-map", str(a.joint_map)] if a.joint_map else []),
        *shlex.split(a.fit_args),
    ]
    if prep(cmd) != 0:
        raise SystemExit("fit-body failed")
    wall = time.perf_counter() - t0
    report = json.loads((fitted / "fit" / "report.json").read_text())
    res = {
        "command": "PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fit_body.py "
        + shlex.join(sys.argv[1:]),
        "machine": f"{platform.system()} {platform.machine()}, CPU only, torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread(s)",
        "keypoints": {
            "noise_px": 2.0,
            "outlier_fraction": 0.1,
            "drop_fraction": 0.2,
            "format": a.format,
            "seed": a.seed,
        },
        "capture": str(a.capture),
        "frames": cap.num_frames,
        "views": len(names),
        "fit_body_wall_s": round(wall, 1),
        "report": {k: report[k] for k in ("reprojection_px", "inliers", "seconds", "shards")},
        "errors": errors(cap, load_capture(fitted), jm),
    }
    res["report"]["reprojection_px"] = {k: v for k, v in res["report"]["reprojection_px"].items() if k != "per_frame"}
    print(json.dumps(res["errors"]), flush=True)
    if not a.no_scaling:
        res["scaling"] = scaling(cap, jm, a.frames, a.views)
    if a.train:
        res["train"] = train_compare(a.capture, fitted, a.work, a.true_dataset, a.preset)
        print(json.dumps(res["train"]))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
