"""``avatar-drive``: drive a trained avatar with a motion and write frames, a video, latents and metrics.

    avatar-drive --run runs/ours --motion capture_b --out drive/b                    # another capture: + metrics
    avatar-drive --run runs/ours --motion cap --split test --mode reinit --out d     # paper's "re-init. 30"
    avatar-drive --run runs/ours --motion 01_01.bvh --cameras orbit --out d          # CMU mocap, orbit cameras
    avatar-drive --run runs/ours --motion m.npz --motion-fps 60 --out d              # resampled to training fps
    avatar-drive --run runs/ours --motion cap --view                                 # browser viewer, 127.0.0.1:8080
    avatar-drive --run runs/ours --motion cap --export-ply plys --up-axis -y        # 3DGS PLY per frame
    avatar-drive --run runs/imported --motion Boxing_Toes.bvh --cameras orbit --out d # any BVH names, any rig
    avatar-drive --run runs/imported --motion m.bvh --joint-map map.json --out d     # {"rig joint": "BVH joint"}
    avatar-drive --run runs/imported --motion amass.npz --cameras orbit --out d      # AMASS SMPL-X (poses, trans)

Outputs in OUT: ``frames/{cam}/{t:06d}.png``, ``drive.mp4`` (cameras side by side),
``latents.npz`` (latents [T, A, L] + the resampled motion), ``drive.json`` (summary);
with ground truth (a capture as motion, capture cameras) also ``metrics.json`` and
``stability.png`` (the paper's figure 7); ``--ramp-up N`` adds ``ramp_up.json/png``.
``--view`` serves the driven avatar to a browser instead (:mod:`gsavatar.drive.viewer`; writes nothing,
``--out`` not needed); ``--export-ply DIR`` writes ``DIR/{t:06d}.ply`` (standard 3DGS, posed), with
or without ``--out``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import tyro

from gsavatar.data_schema import SchemaError, check_images
from gsavatar.data_schema.views import UndistortMaps
from gsavatar.drive.driver import DriveConfig, Driver, load_predictor_for, texture_source
from gsavatar.drive.live import export_drive_plys
from gsavatar.drive.metrics import SequenceMetrics, load_ground_truth, measure_ramp_up, write_ramp_up
from gsavatar.drive.motion import load_driving_motion
from gsavatar.drive.viewer import serve_drive_args
from gsavatar.runs.load import load_run, predictor_from_checkpoint
from gsavatar.metrics.lpips import LPIPSMode, load_lpips
from gsavatar.metrics.protocols import PROTOCOLS, load_ag_lpips
from gsavatar.utils.cli import parse_args, run_reporting_errors
from gsavatar.utils.io import atomic_path, atomic_save_npz, atomic_write_json, write_image
from gsavatar.utils.outdir import claim_output_dir
from gsavatar.utils.paths import output_path
from gsavatar.utils.progress import progress_bar


@dataclass(kw_only=True)
class DriveArgs:
    """Drive a trained avatar with a motion (npz, capture directory or BVH)."""

    drive: Annotated[DriveConfig, tyro.conf.arg(name="")] = field(default_factory=DriveConfig)
    """The drive's configuration: latent source (``--mode``), cameras, image scale, device (flags without a prefix)."""
    run: Path
    """Run directory of ``avatar-train avatar`` (its predictor in RUN/predictor when trained)."""
    motion: Path
    """Driving motion: a motion.npz, a capture directory (ground truth -> metrics), a .bvh file or an AMASS-style
    SMPL-X .npz (poses [F,165], trans, mocap_frame_rate; SMPL-X rigs)."""
    out: Path | None = None
    """Output directory (required unless --view or --export-ply)."""
    predictor: Path | None = None
    """Appearance predictor checkpoint to drive with instead of RUN/predictor/latest.pt (e.g. an ablation trained
    with ``avatar-train predictor --out DIR``: DIR/latest.pt)."""
    motion_fps: float = 0.0
    """Frame rate of an npz motion (0: from an 'fps' array, a sidecar <name>.json or a capture.json beside it)."""
    joint_map: Path | None = None
    """BVH motions: JSON object {"<rig joint>": "<BVH joint>" or null} overriding the joint-name matching
    (CMU, Biovision, Mixamo and SMPL-X names are matched without it; docs/import.md)."""
    amass_up: Literal["z", "y"] = "z"
    """AMASS motions: the file's up axis (z: AMASS's own, turned to the avatar's Y up; y: taken as it is)."""
    split: str | None = None
    """Capture motions: drive with this split's frames (e.g. ``test``); default all frames."""
    start: int = 0
    """First source frame."""
    count: int = 0
    """Source frames to use (BVH: output frames); 0 = to the end."""
    write_frames: bool = True
    """Write every render as frames/{cam}/{t:06d}.png."""
    lpips: LPIPSMode = "auto"
    """LPIPS metric: ``auto`` uses it when its weights load, ``on`` requires it, ``off`` skips it."""
    ag_lpips: Literal["auto", "on", "off"] = "auto"
    """LPIPS (VGG and Alex) of the field's ``ag`` protocol: ``auto`` = on CUDA only (5-15 s per view on a CPU)."""
    ag_lpips_every: int = 10
    """The ``ag`` protocol's LPIPS on every N-th frame (its PSNR and SSIM on every frame)."""
    ramp_up: int = 0
    """Also measure the first N frames after zero / pose / encoder initialisation (needs ground truth + textures)."""
    force: bool = False
    """Write into a non-empty ``out`` that is not an avatar-drive output (refused otherwise, so a user's
    files are never overwritten). An earlier drive's folder is reused without it."""
    view: bool = False
    """Serve a browser viewer of the driven avatar (gsavatar.drive.viewer) instead of writing outputs."""
    port: int = 8080
    """--view: port of the page."""
    host: str = "127.0.0.1"
    """--view: interface to bind (default: this machine only)."""
    start_paused: bool = False
    """--view: open paused on the first frame."""
    sh0_only: bool = False
    """--view: colour from SH band 0 only (view independent)."""
    export_ply: Path | None = None
    """Write every driven frame's posed Gaussians as DIR/{t:06d}.ply (standard 3DGS layout)."""
    up_axis: Literal["y", "-y", "z"] = "y"
    """--export-ply: up axis of the files (``y``: ours; ``-y``: COLMAP/3DGS viewers such as SuperSplat; ``z``: Z-up
    tools)."""

    def config(self) -> DriveConfig:
        """The drive configuration these arguments hold."""
        return self.drive


def _json_safe(obj):
    """NaN/Inf -> None (strict JSON): NaN = empty mask, +Inf PSNR = identical images."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _tile(images: dict[str, torch.Tensor]) -> np.ndarray:
    """Cameras side by side, padded to even size (yuv420p). -> [H, W, 3] uint8"""
    H = max(v.shape[0] for v in images.values())
    cols = []
    for v in images.values():
        a = (v.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        cols.append(np.pad(a, ((0, H - a.shape[0]), (0, 0), (0, 0))))
    img = np.concatenate(cols, 1)
    return np.pad(img, ((0, img.shape[0] % 2), (0, img.shape[1] % 2), (0, 0)))


def drive(args: DriveArgs) -> dict:
    """Run ``avatar-drive`` (see module docstring); returns the drive.json summary."""
    import imageio.v2 as imageio

    cfg = args.config()
    if args.motion_fps < 0 or args.count < 0 or args.ramp_up < 0:
        raise ValueError("motion_fps, count and ramp_up must be >= 0")
    loaded = load_run(args.run, cfg.device)
    # the ramp-up drives the predictor modes too, whatever this drive's mode needs
    predictor = load_predictor_for(args.run) if args.ramp_up and loaded.net.avatar.latent_in else "auto"
    if args.predictor is not None:
        if not Path(args.predictor).is_file():
            raise FileNotFoundError(f"--predictor {args.predictor}: no such checkpoint file")
        predictor = predictor_from_checkpoint(Path(args.predictor))
    d = Driver(args.run, cfg, loaded=loaded, predictor=predictor)
    scene = d.scene
    with warnings.catch_warnings(record=True) as caught:  # e.g. rig joints no BVH joint drives: one line each
        warnings.simplefilter("always")
        motion = load_driving_motion(
            args.motion,
            scene.capture.rig,
            d.fps,
            fps=args.motion_fps or None,
            start=args.start,
            count=args.count or None,
            split=args.split,
            joint_map=args.joint_map,
            amass_up=args.amass_up,
        )
    motion_warnings = [str(w.message) for w in caught]
    for w in motion_warnings:
        print(f"warning: {w}", file=sys.stderr)
    if motion.face is not None and motion.face.shape[1] != d.face_dim:
        raise SchemaError(args.motion, "face", f"has {motion.face.shape[1]} columns, the avatar expects {d.face_dim}")
    gt = motion.gt if cfg.cameras == "capture" else None
    if motion.gt is not None:
        d.use_capture_cameras(motion.gt.capture)
    if gt is not None:  # missing or misfit ground truth fails here, before OUT is touched
        check_images(gt.capture, sorted(set(gt.frames)), [v.name for v in d.views])
    textures = texture_source(motion, scene, cfg.textures) if d.needs_textures else None
    lp, lp_name = load_lpips(args.lpips, d.device, fallback=True) if gt is not None else (None, "off")
    ag_nets, ag_names = load_ag_lpips(d.device, args.ag_lpips if gt is not None and args.lpips != "off" else "off")
    acc = SequenceMetrics(lp, d.bg, ag_nets, args.ag_lpips_every)
    maps = UndistortMaps()  # undistortion tables of the ground-truth cameras, built once for the sequence
    out = claim_output_dir(Path(args.out), "drive", args.force, register=True)
    cams = [v.name for v in d.views]
    T = motion.num_frames
    fps_video = cfg.video_fps or motion.fps
    latents = []
    t0 = time.perf_counter()
    video = out / "drive.mp4"
    with atomic_path(video, suffix=".mp4") as tmp, progress_bar(f"avatar-drive {cfg.mode} ({T} frames)", T) as bar:
        writer = imageio.get_writer(tmp, fps=fps_video, macro_block_size=1, format="FFMPEG")
        try:
            for fr in d.frames(motion, textures):
                t = fr.t
                if t == 0:
                    cams = [v.name for v in d.views]  # orbit views are placed by start()
                latents.append(fr.latents.numpy())
                gts = (
                    load_ground_truth(gt.capture, gt.frames[t], cams, cfg.image_scale, d.bg, maps)
                    if gt is not None
                    else {}
                )
                for c in cams:
                    g = gts.get(c)
                    acc.add(t, c, fr.images[c], fr.alphas[c], None if g is None else g[0], None if g is None else g[1])
                    if args.write_frames:
                        write_image(output_path(out, "frames", c, f"{t:06d}.png"), fr.images[c].numpy())
                writer.append_data(_tile(fr.images))
                bar.advance()
        finally:
            writer.close()
    seconds = time.perf_counter() - t0
    lat = np.stack(latents).astype(np.float32)
    arrays = {
        "latents": lat,
        "pose": motion.pose,
        "root_rotation": motion.root_rotation,
        "root_translation": motion.root_translation,
        "fps": np.float32(motion.fps),
    }
    if motion.face is not None:
        arrays["face"] = motion.face
    atomic_save_npz(out / "latents.npz", **arrays)
    summary = acc.summary()
    info = {
        "run": str(args.run),
        "motion": motion.source,
        "mode": cfg.mode,
        "frames": T,
        "fps": motion.fps,
        "source_fps": motion.source_fps,
        "resampled": abs(motion.fps - motion.source_fps) > 1e-9,
        "cameras": cams,
        "video": str(video),
        "video_fps": fps_video,
        "seconds": round(seconds, 3),
        "ground_truth": gt is not None,
        "render_change": summary["mean"].get("render_change"),
        "motion_warnings": motion_warnings,
        "config": json.loads(json.dumps(dataclasses.asdict(cfg), default=str)),
    }
    if gt is not None:
        fig = acc.write_figure(out / "stability.png")
        metrics = {
            "mode": cfg.mode,
            "lpips_net": lp_name,
            "protocols": dict(PROTOCOLS),
            "ag_lpips_nets": ag_names,
            "ag_lpips_every": args.ag_lpips_every,
            "gt_frames": gt.frames,
            **summary,
            "stability_figure": None if fig is None else fig.name,
        }
        atomic_write_json(out / "metrics.json", _json_safe(metrics))
        info["metrics"] = summary["mean"]
    if args.ramp_up:
        tex = textures or texture_source(motion, scene, cfg.textures)
        res = measure_ramp_up(d, motion, tex, args.ramp_up, with_images=gt is not None)
        write_ramp_up(_json_safe(res), out)
        info["ramp_up"] = {
            m: {"latent_l1_first": v["latent_l1"][0], "latent_l1_last": v["latent_l1"][-1]}
            for m, v in res["modes"].items()
        }
    atomic_write_json(out / "drive.json", _json_safe(info))
    print(f"avatar-drive: {T} frames x {len(cams)} cameras in {seconds:.1f}s -> {out}")
    if gt is not None:
        print("metrics: " + ", ".join(f"{k} {v:.4f}" for k, v in summary["mean"].items() if v is not None))
    return info


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``avatar-drive``; returns the exit code (2: bad input, message on stderr)."""
    # parse errors and DriveConfig's field validation: exit 2 naming the field
    args = parse_args(lambda: tyro.cli(DriveArgs, args=argv, prog="avatar-drive", description=__doc__), exit_codes=True)
    if isinstance(args, int):
        return args
    if args.view:
        return run_reporting_errors(lambda: serve_drive_args(args))
    if args.export_ply is not None:
        rc = run_reporting_errors(lambda: export_drive_plys(args))
        if rc or args.out is None:
            return rc
    if args.out is None:
        print("error: --out is required (unless --view or --export-ply)", file=sys.stderr)
        return 2
    return run_reporting_errors(lambda: drive(args))


if __name__ == "__main__":
    raise SystemExit(main())
