"""``avatar-prep fit-body``: a capture's body poses from multi-view 2D keypoints.

    avatar-prep fit-body --capture C --keypoints DIR --out C2 [--format body25|coco_wholebody] [--joint-map F]

Reads the keypoints (:mod:`gsavatar.fitting.keypoints`), triangulates them robustly
(:mod:`gsavatar.fitting.triangulate`), fits the capture's rig shard by shard
(:mod:`gsavatar.fitting.fit`) and writes ``C2``: a capture (format v1) with C's cameras, template, images and
masks (linked) and the fitted ``motion.npz``, which ``avatar-prep all`` takes unchanged. ``C2/fit/`` holds
``report.json`` (per-frame reprojection error, triangulation inliers, skipped frames, timings), one
``shards/shard-NNNNN.npz`` per shard (a re-run reuses the shards whose inputs and settings are unchanged)
and ``overlay.png`` (the fitted skeleton and the detections over one image per camera).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from gsavatar.data_schema import load_capture
from gsavatar.data_schema.capture import Motion, write_capture_metadata
from gsavatar.fitting.fit import FitConfig, fit_sequence
from gsavatar.fitting.keypoints import detect_format, load_joint_map, read_keypoints
from gsavatar.fitting.triangulate import project_world, triangulate
from gsavatar.geometry.lbs import pose_joints
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_link, atomic_save_npz, atomic_write_json, read_image, read_npz, write_image
from gsavatar.utils.outdir import claim_output_dir
from gsavatar.utils.progress import progress_bar

MIN_POINTS = 3
"""A frame needs this many triangulated mapped keypoints to count as seen (fewer: a recorded skip)."""


@dataclass
class FitBody:
    """Fit the capture's body (rig pose + root motion) to multi-view 2D keypoints; write a capture with it."""

    capture: Path
    """Input capture (cameras, template and rig, images, masks; its motion.npz is replaced)."""
    keypoints: Path
    """Keypoint folder: ``<camera>/<frame>*.json`` (OpenPose BODY_25 or COCO-WholeBody files)."""
    out: Path
    """Output capture folder (new or empty, or a previous fit-body output to resume)."""
    format: Literal["auto", "body25", "coco_wholebody"] = "auto"
    """Keypoint format; ``auto`` reads it from the first file."""
    joint_map: Path | None = None
    """JSON keypoint -> rig joint map replacing the package's one for the format (``gsavatar/fitting/maps``)."""
    shard_frames: int = 100
    """Frames fitted together (temporal smoothness acts inside a shard); one resumable file per shard."""
    link: Literal["symlink", "hardlink", "copy"] = "symlink"
    """How images, masks and the template get into the output capture."""
    fit: FitConfig = field(default_factory=FitConfig)
    """Fit weights and schedule."""
    force: bool = False
    """Write into a non-empty folder that is not a gsavatar capture."""

    def run(self) -> None:
        fit_body(self)


FIT_VERSION = 2
"""Bumped whenever the fit's result for the same inputs changes (shards of another version are refitted)."""


def _fingerprint(keypoints: np.ndarray, args: FitBody, joint_map) -> str:
    h = hashlib.sha256(np.ascontiguousarray(keypoints, np.float64).tobytes())
    h.update(f"fit-body v{FIT_VERSION}".encode())
    h.update(json.dumps(dataclasses.asdict(args.fit), sort_keys=True).encode())
    h.update(np.asarray(joint_map.keypoints).tobytes() + np.asarray(joint_map.joints).tobytes())
    return h.hexdigest()[:16]


def _link_tree(src: Path, dst: Path, how: str) -> int:
    n = 0
    for p in sorted(src.rglob("*")):
        if p.is_file():
            atomic_link(p.resolve(), dst / p.relative_to(src), how)
            n += 1
    return n


def fit_body(args: FitBody) -> dict:
    """The command (module docstring). -> the report."""
    cap = load_capture(args.capture)
    if Path(args.out).resolve() == Path(args.capture).resolve():
        raise SchemaError(args.out, "", "is the input capture; fit-body writes a new capture (choose another --out)")
    if args.shard_frames < 1:
        raise ValueError(f"--shard-frames must be >= 1, got {args.shard_frames}")
    fmt = detect_format(args.keypoints) if args.format == "auto" else args.format
    jm = load_joint_map(fmt, cap.rig, args.joint_map, cap.template)
    names = sorted(cap.cameras)
    cams = [cap.cameras[n] for n in names]
    frames = list(range(cap.num_frames))
    kp = read_keypoints(
        args.keypoints, names, frames, fmt, {n: (cap.cameras[n].width, cap.cameras[n].height) for n in names}
    )
    views_with = (kp[..., 2] > 0).any(-1)  # [F, C]
    if not views_with.any():
        raise SchemaError(
            args.keypoints,
            "",
            f"no detections in any view of any of the {len(frames)} frames (format {fmt}; folders {names[:4]}...)",
        )
    out = claim_output_dir(Path(args.out), "capture", args.force, register=True)
    t0 = time.perf_counter()
    tri = triangulate(kp, cams, args.fit.min_confidence, args.fit.threshold_px)
    t_tri = time.perf_counter() - t0
    seen = np.isfinite(tri.points[:, jm.keypoints]).all(-1).sum(1) >= MIN_POINTS  # [F]
    if not seen.any():
        raise SchemaError(
            args.keypoints,
            "",
            f"the person is not found in enough views in any frame (needs {MIN_POINTS} "
            "keypoints seen by >= 2 agreeing views)",
        )
    fp = _fingerprint(kp, args, jm)
    shard_dir = out / "fit" / "shards"
    results, reused, t_fit = [], 0, 0.0
    S = args.shard_frames
    n_shards = (len(frames) + S - 1) // S
    with progress_bar(f"fit-body ({len(frames)} frames, {len(names)} views)", n_shards) as bar:
        for i in range(n_shards):
            a, b = i * S, min((i + 1) * S, len(frames))
            path = shard_dir / f"shard-{i:05d}.npz"
            if path.exists():
                z = read_npz(path)
                if str(z.get("fingerprint", "")) == fp and z["pose"].shape[0] == b - a:
                    results.append({k: z[k] for k in ("pose", "root_rotation", "root_translation", "reprojection_px")})
                    reused += 1
                    bar.advance()
                    continue
            t1 = time.perf_counter()
            r = fit_sequence(cap.rig, cams, kp[a:b], jm, tri.points[a:b], tri.inliers[a:b], args.fit)
            t_fit += time.perf_counter() - t1
            atomic_save_npz(path, fingerprint=np.array(fp), **r)
            results.append(r)
            bar.advance()
    res = {k: np.concatenate([r[k] for r in results]) for k in results[0]}
    motion = Motion(res["pose"], res["root_rotation"], res["root_translation"], cap.motion.face)
    # the capture: metadata rewritten, template/images/masks linked, the fitted motion
    for sub in ("template", "images", "masks"):
        _link_tree(Path(args.capture) / sub, out / sub, args.link)
    write_capture_metadata(out, cap.fps, cap.num_frames, cap.cameras, cap.splits)
    motion.save(out / "motion.npz")
    inl = tri.inliers[:, jm.keypoints]  # [F, M, C]
    det = (kp[:, :, jm.keypoints, 2] >= args.fit.min_confidence).transpose(0, 2, 1)  # [F, M, C]
    rep = res["reprojection_px"]
    report = {
        "format": fmt,
        "keypoints": list(jm.names),
        "frames": len(frames),
        "views": names,
        "reprojection_px": {
            "mean": float(np.nanmean(rep)),
            "median": float(np.nanmedian(rep)),
            "max": float(np.nanmax(rep)),
            "per_frame": [None if not np.isfinite(v) else float(v) for v in rep],
        },
        "inliers": {
            "detections": int(det.sum()),
            "inlier_detections": int(inl.sum()),
            "fraction": float(inl.sum() / max(det.sum(), 1)),
            "per_keypoint": {n: float(inl[:, m].sum() / max(det[:, m].sum(), 1)) for m, n in enumerate(jm.names)},
        },
        "skipped_frames": [int(f) for f in np.flatnonzero(~seen)],
        "skipped_note": f"frames with fewer than {MIN_POINTS} triangulated keypoints: their poses come from the "
        "neighbouring frames through the smoothness and prior terms",
        "views_without_detections": {n: int((~views_with[:, c]).sum()) for c, n in enumerate(names)},
        "seconds": {
            "triangulation": round(t_tri, 3),
            "fit": round(t_fit, 3),
            "fit_per_frame": round(t_fit / max(len(frames) - reused * S, 1), 4),
        },
        "shards": {"total": n_shards, "reused": reused},
        "config": dataclasses.asdict(args.fit),
    }
    overlay = out / "fit" / "overlay.png"
    write_image(
        overlay,
        overlay_picture(cap, cams, names, kp, tri, jm, res, int(np.flatnonzero(seen)[len(np.flatnonzero(seen)) // 2])),
    )
    report["overlay"] = str(overlay.relative_to(out))
    atomic_write_json(out / "fit" / "report.json", report)
    print(
        f"fit-body: {len(frames)} frames, {len(names)} views, reprojection {report['reprojection_px']['mean']:.2f} px "
        f"(median {report['reprojection_px']['median']:.2f}), {100 * report['inliers']['fraction']:.1f}% of the "
        f"detections inliers, {len(report['skipped_frames'])} frames skipped -> {out}"
    )
    return report


def overlay_picture(cap, cams, names, kp, tri, jm, res, frame: int, tile: int = 256) -> np.ndarray:
    """The fitted skeleton (white bones, blue joints) and the frame's detections (green: inlier, red: rejected)
    over each camera's image of ``frame``, tiled in a grid. -> [H, W, 3] float32 in [0, 1]"""
    with torch.no_grad():
        J = pose_joints(
            cap.rig,
            *(
                torch.as_tensor(res[k][frame : frame + 1], dtype=torch.float64)
                for k in ("pose", "root_rotation", "root_translation")
            ),
        )[0].numpy()
    parents = cap.rig.parents()
    pix, _ = project_world(J, cams)  # [J, C, 2]
    tiles = []
    for c, name in enumerate(names):
        img = np.ascontiguousarray(read_image(cap.image_path(name, frame))[..., :3], np.float32)
        s = tile / max(img.shape[:2])
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)))
        img = np.ascontiguousarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8))  # cv2 draws text on 8 bit
        P = (pix[:, c] * s).round().astype(int)
        for j, p in enumerate(parents):
            if p >= 0:
                cv2.line(img, tuple(P[p]), tuple(P[j]), (255, 255, 255), 1, cv2.LINE_AA)
        for j in range(len(J)):
            cv2.circle(img, tuple(P[j]), 2, (50, 100, 255), -1)
        for m, k in enumerate(jm.keypoints):
            x, y, conf = kp[frame, c, k]
            if conf > 0:
                col = (25, 230, 25) if tri.inliers[frame, k, c] else (255, 25, 25)
                cv2.drawMarker(img, (round(x * s), round(y * s)), col, cv2.MARKER_CROSS, 7, 1)
        cv2.putText(img, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1, cv2.LINE_AA)
        canvas = np.zeros((tile, tile, 3), np.float32)
        canvas[: img.shape[0], : img.shape[1]] = img / 255.0
        tiles.append(canvas)
    cols = min(4, len(tiles))
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + cols], 1) for i in range(0, len(tiles), cols)]
    return np.concatenate(rows, 0)
