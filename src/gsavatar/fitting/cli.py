"""``avatar-prep fit-body``: a capture's body poses from multi-view 2D keypoints.

    avatar-prep fit-body --capture C --keypoints DIR --out C2 [--format body25|coco_wholebody] [--joint-map F]

Reads the keypoints (:mod:`gsavatar.fitting.keypoints`), triangulates them robustly
(:mod:`gsavatar.fitting.triangulate`), fits the capture's rig shard by shard
(:mod:`gsavatar.fitting.fit`) and writes ``C2``: a capture (format v1) with C's cameras, template, images and
masks (linked) and the fitted ``motion.npz``, which ``avatar-prep all`` takes unchanged. ``C2/fit/`` holds
``report.json`` (per-frame reprojection error, triangulation inliers, skipped frames, timings), one
``shards/shard-NNNNN.npz`` per shard (a re-run reuses the shards whose inputs and settings are unchanged)
and ``overlay.png`` (the fitted skeleton and the detections over one image per camera).

With ``--smplx-model`` (a capture whose body ``avatar-prep import`` made from that model) the body's shape is fitted
too: first one ``betas`` for the whole sequence, with the poses of ``--shape-frames`` frames spread over it
(``C2/fit/shape.npz``), then every shard's poses on the body of that shape; ``C2/template`` is the model at the
fitted betas (the capture's faces, UVs and skin weights kept) and its rig.
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
from gsavatar.data_schema.template import save_template
from gsavatar.fitting.fit import FitConfig, ShapeBasis, Silhouette, fit_sequence, silhouette_distance, surface_subset
from gsavatar.fitting.keypoints import detect_format, load_joint_map, read_keypoints
from gsavatar.fitting.prior import pose_prior_stats
from gsavatar.fitting.triangulate import project_world, triangulate
from gsavatar.geometry.lbs import pose_joints
from gsavatar.importers.smplx_body import shaped_vertices, smplx_rig, smplx_shape_basis
from gsavatar.importers.smplx_model import SMPLX_JOINT_NAMES, load_smplx_model
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import (
    atomic_link,
    atomic_save_npz,
    atomic_write_json,
    read_image,
    read_mask,
    read_npz,
    write_image,
)
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
    """Keypoint -> rig joint map replacing the package's one for the format: a JSON file, or the name of a packaged
    map (``body25_hands``: BODY_25 plus OpenPose's hand points, docs/fit_body.md)."""
    shard_frames: int = 100
    """Frames fitted together (temporal smoothness acts inside a shard); one resumable file per shard."""
    link: Literal["symlink", "hardlink", "copy"] = "symlink"
    """How images, masks and the template get into the output capture."""
    fit: FitConfig = field(default_factory=FitConfig)
    """Fit weights and schedule."""
    smplx_model: Path | None = None
    """The SMPL-X model file (``SMPLX_NEUTRAL.npz``) the capture's body was imported from: fit its shape too (one
    ``betas`` per sequence) and write the reshaped template. Default: keep the capture's template (the anny body of
    the synthetic captures has no linear shape space)."""
    pose_prior: tuple[Path, ...] = ()
    """Motion capture of the same skeleton whose mean pose centres the pose prior and starts the fit: BVH files
    (retargeted onto the capture's rig) or ``.npz`` files with ``pose`` [F, P] (e.g. another capture's
    ``motion.npz``). Default: the rest pose. Decides what no keypoint sees (limb twist, fingers, the split of a
    torso rotation between the root and pass-through joints; docs/fit_body.md)."""
    pose_prior_spread: bool = True
    """With ``--pose-prior``: scale the prior per parameter by that motion's spread (a degree of freedom real motion
    hardly moves is held near its mean; ``--fit.prior-std-floor``); False: 1 rad everywhere, the mean only."""
    num_betas: int = 10
    """Shape coefficients fitted with ``--smplx-model``."""
    shape_frames: int = 60
    """Frames, spread evenly over the sequence, whose poses are fitted together with the shape."""
    shape_steps: int = 1500
    """Adam steps of the shape stage on pose + root + shape (after ``--fit.root-steps`` on the root alone); the
    shards' pose fit then takes ``--fit.steps``."""
    silhouette_points: int = 500
    """Template surface points the silhouette term poses (farthest-point subset of the vertices); the term is on
    when ``--fit.w-silhouette`` > 0."""
    silhouette_size: int = 128
    """Longer side of the masks' distance maps the silhouette term samples (pixels; distances stay in full-image
    pixels)."""
    force: bool = False
    """Write into a non-empty folder that is not a gsavatar capture."""

    def run(self) -> None:
        fit_body(self)


FIT_VERSION = 3
"""Bumped whenever the fit's result for the same inputs changes (shards of another version are refitted)."""


def _fingerprint(keypoints: np.ndarray, args: FitBody, joint_map, *extra: bytes) -> str:
    h = hashlib.sha256(np.ascontiguousarray(keypoints, np.float64).tobytes())
    h.update(f"fit-body v{FIT_VERSION}".encode())
    h.update(json.dumps(dataclasses.asdict(args.fit), sort_keys=True).encode())
    h.update(np.asarray(joint_map.keypoints).tobytes() + np.asarray(joint_map.joints).tobytes())
    h.update(np.ascontiguousarray(joint_map.rest_offsets(), np.float64).tobytes())
    for e in extra:
        h.update(e)
    return h.hexdigest()[:16]


def _smplx_body(path: Path, cap):
    """The SMPL-X model of ``path`` after checking that ``cap``'s body was made from it. -> model"""
    model = load_smplx_model(path)
    names = tuple(j.name for j in cap.rig.joints)
    if names != SMPLX_JOINT_NAMES:
        raise SchemaError(
            Path(cap.root) / "template" / "rig.json",
            "joints",
            f"is not an SMPL-X rig ({len(names)} joints, first {list(names[:3])}); --smplx-model needs a capture "
            "whose body `avatar-prep import` made from that model",
        )
    if len(cap.template.vertices) != model.num_vertices:
        raise SchemaError(
            Path(cap.root) / "template" / "mesh.obj",
            "v",
            f"has {len(cap.template.vertices)} vertices, the model {path} {model.num_vertices}: not its body",
        )
    return model


def _shaped_body(model, cap, betas: np.ndarray):
    """The capture's template (faces, UVs, skin weights, face mask kept) with the model's vertices at ``betas``,
    and the SMPL-X rig of that shape. -> (template, rig)"""
    verts = shaped_vertices(model, betas)
    t = dataclasses.replace(cap.template, vertices=verts.astype(np.float32))
    return t, smplx_rig(model, model.J_regressor.astype(np.float64) @ verts)


def fit_shape(
    args: FitBody,
    cap,
    model,
    fmt: str,
    kp,
    tri,
    seen: np.ndarray,
    out: Path,
    prior_mean: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """One shape for the sequence: ``betas`` fitted with the poses of up to ``args.shape_frames`` seen frames spread
    over it (no temporal terms: the frames are not neighbours); reused from ``out/fit/shape.npz`` when its inputs
    and settings are unchanged. -> (betas [B] float64, report entry)"""
    heads0, dheads = smplx_shape_basis(model, args.num_betas)
    mean_t, mean_rig = _shaped_body(model, cap, np.zeros(dheads.shape[0]))
    jm = load_joint_map(fmt, mean_rig, args.joint_map, mean_t)
    idx = np.flatnonzero(seen)
    sel = idx[np.unique(np.linspace(0, len(idx) - 1, min(args.shape_frames, len(idx))).round().astype(int))]
    model_sha = hashlib.sha256(Path(model.path).read_bytes()).hexdigest()
    fp = _fingerprint(
        kp[sel],
        args,
        jm,
        b"shape",
        sel.tobytes(),
        f"{dheads.shape[0]} {args.shape_steps}".encode(),
        model_sha.encode(),
        b"" if prior_mean is None else np.asarray(prior_mean, np.float64).tobytes(),
        b"" if prior_std is None else b"spread" + np.asarray(prior_std, np.float64).tobytes(),
    )
    path = out / "fit" / "shape.npz"
    t0 = time.perf_counter()
    if path.exists() and str(read_npz(path).get("fingerprint", "")) == fp:
        betas, reused = read_npz(path)["betas"].astype(np.float64), True
    else:
        cfg = dataclasses.replace(args.fit, w_smooth=0.0, w_smooth_pose=0.0, steps=args.shape_steps)
        with progress_bar(
            f"fit-body shape ({len(sel)} frames, {dheads.shape[0]} betas)", cfg.root_steps + cfg.steps
        ) as bar:
            r = fit_sequence(
                mean_rig,
                [cap.cameras[n] for n in sorted(cap.cameras)],
                kp[sel],
                jm,
                tri.points[sel],
                tri.inliers[sel],
                cfg,
                progress=lambda i, n: bar.advance(),
                shape=ShapeBasis(heads0, dheads),
                prior_mean=prior_mean,
                prior_std=prior_std,
            )
        betas, reused = r["betas"].astype(np.float64), False
        atomic_save_npz(path, fingerprint=np.array(fp), betas=betas, frames=sel)
    entry = {
        "model": str(model.path),
        "betas": [float(b) for b in betas],
        "frames": [int(f) for f in sel],
        "reused": reused,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return betas, entry


def shard_silhouette(cap, template, names: list[str], frames: range, points: np.ndarray, size: int) -> Silhouette:
    """The silhouette term's inputs for ``frames``: every camera's mask as a distance map with the longer side
    ``size`` (same shape for all cameras: the largest image's aspect), the template's ``points`` subset."""
    sizes = np.array([(cap.cameras[n].width, cap.cameras[n].height) for n in names], np.float64)
    W, H = sizes.max(0)
    s = size / max(W, H)
    wh = (max(1, round(W * s)), max(1, round(H * s)))
    dist = np.empty((len(frames), len(names), wh[1], wh[0]), np.float32)
    for i, f in enumerate(frames):
        for c, n in enumerate(names):
            path = cap.mask_path(n, f)
            mask = read_mask(path)
            if mask.shape != (cap.cameras[n].height, cap.cameras[n].width):
                raise SchemaError(
                    path,
                    "",
                    f"mask is {mask.shape[1]}x{mask.shape[0]}, camera {n} is {cap.cameras[n].width}x"
                    f"{cap.cameras[n].height}: the silhouette term needs masks at the image size",
                )
            dist[i, c] = silhouette_distance(mask, wh)
    return Silhouette(
        np.asarray(template.vertices, np.float64)[points],
        np.asarray(template.skin_indices)[points],
        np.asarray(template.skin_weights, np.float64)[points],
        dist,
        sizes,
    )


def _masks_digest(cap, names: list[str], frames: list[int]) -> bytes:
    """SHA-256 of every camera's mask file of every frame; SchemaError naming the first one missing."""
    h = hashlib.sha256()
    for n in names:
        for f in frames:
            path = cap.mask_path(n, f)
            if not path.is_file():
                raise SchemaError(path, "", "mask file not found (--fit.w-silhouette > 0 reads every frame's masks)")
            h.update(path.read_bytes())
    return h.digest()


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
    if args.fit.w_silhouette > 0 and min(args.silhouette_points, args.silhouette_size) < 1:
        raise ValueError(
            f"--silhouette-points and --silhouette-size must be >= 1 with --fit.w-silhouette > 0, got "
            f"{args.silhouette_points}, {args.silhouette_size}"
        )
    fmt = detect_format(args.keypoints) if args.format == "auto" else args.format
    model = None if args.smplx_model is None else _smplx_body(Path(args.smplx_model), cap)
    if model is not None:
        if min(args.num_betas, args.shape_frames, args.shape_steps) < 1:
            raise ValueError(
                f"--num-betas, --shape-frames and --shape-steps must be >= 1, got {args.num_betas}, "
                f"{args.shape_frames}, {args.shape_steps}"
            )
        if args.num_betas > model.num_betas:
            raise SchemaError(
                Path(args.smplx_model),
                "shapedirs",
                f"has {model.num_betas} shape components, --num-betas asks {args.num_betas}",
            )
    jm = load_joint_map(fmt, cap.rig, args.joint_map, cap.template)
    prior_mean, prior_std, prior_entry = (
        pose_prior_stats(args.pose_prior, cap.rig) if args.pose_prior else (None, None, None)
    )
    if prior_entry is not None:
        prior_entry["spread"] = args.pose_prior_spread
        if not args.pose_prior_spread:
            prior_std = None
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
    # the silhouette term reads every frame's masks: all must be there before anything is written, and their
    # contents are inputs of the fit (regenerated masks refit the shards)
    masks_digest = _masks_digest(cap, names, frames) if args.fit.w_silhouette > 0 else b""
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
    template, rig, shape_entry, extra = cap.template, cap.rig, None, b""
    if model is not None:
        betas, shape_entry = fit_shape(args, cap, model, fmt, kp, tri, seen, out, prior_mean, prior_std)
        template, rig = _shaped_body(model, cap, betas)
        jm = load_joint_map(fmt, rig, args.joint_map, template)
        extra = np.asarray(betas, np.float64).tobytes()
    use_sil = args.fit.w_silhouette > 0
    sil_points = surface_subset(template, args.silhouette_points) if use_sil else None
    if use_sil:
        extra += f"silhouette {args.silhouette_points} {args.silhouette_size}".encode() + sil_points.tobytes()
        extra += masks_digest
    if prior_mean is not None:
        extra += b"pose prior" + prior_mean.tobytes()
    if prior_std is not None:
        extra += b"spread" + prior_std.tobytes()
    fp = _fingerprint(kp, args, jm, extra)
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
            sil = (
                shard_silhouette(cap, template, names, range(a, b), sil_points, args.silhouette_size)
                if use_sil
                else None
            )
            r = fit_sequence(
                rig,
                cams,
                kp[a:b],
                jm,
                tri.points[a:b],
                tri.inliers[a:b],
                args.fit,
                silhouette=sil,
                prior_mean=prior_mean,
                prior_std=prior_std,
            )
            t_fit += time.perf_counter() - t1
            atomic_save_npz(path, fingerprint=np.array(fp), **r)
            results.append(r)
            bar.advance()
    res = {k: np.concatenate([r[k] for r in results]) for k in results[0]}
    motion = Motion(res["pose"], res["root_rotation"], res["root_translation"], cap.motion.face)
    # the capture: metadata rewritten, template/images/masks linked, the fitted motion
    for sub in ("template", "images", "masks") if model is None else ("images", "masks"):
        _link_tree(Path(args.capture) / sub, out / sub, args.link)
    if model is not None:  # the reshaped body replaces the capture's (written, not linked)
        save_template(template, out / "template")
        rig.save(out / "template" / "rig.json")
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
    if shape_entry is not None:
        report["shape"] = shape_entry
    if prior_entry is not None:
        report["pose_prior"] = prior_entry
    overlay = out / "fit" / "overlay.png"
    write_image(
        overlay,
        overlay_picture(
            cap, rig, cams, names, kp, tri, jm, res, int(np.flatnonzero(seen)[len(np.flatnonzero(seen)) // 2])
        ),
    )
    report["overlay"] = str(overlay.relative_to(out))
    atomic_write_json(out / "fit" / "report.json", report)
    print(
        f"fit-body: {len(frames)} frames, {len(names)} views, reprojection {report['reprojection_px']['mean']:.2f} px "
        f"(median {report['reprojection_px']['median']:.2f}), {100 * report['inliers']['fraction']:.1f}% of the "
        f"detections inliers, {len(report['skipped_frames'])} frames skipped -> {out}"
    )
    return report


def overlay_picture(cap, rig, cams, names, kp, tri, jm, res, frame: int, tile: int = 256) -> np.ndarray:
    """The fitted skeleton (white bones, blue joints) and the frame's detections (green: inlier, red: rejected)
    over each camera's image of ``frame``, tiled in a grid. -> [H, W, 3] float32 in [0, 1]"""
    with torch.no_grad():
        J = pose_joints(
            rig,
            *(
                torch.as_tensor(res[k][frame : frame + 1], dtype=torch.float64)
                for k in ("pose", "root_rotation", "root_translation")
            ),
        )[0].numpy()
    parents = rig.parents()
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
