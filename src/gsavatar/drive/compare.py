"""One test frame, four latent sources: ground truth | encoder | predictor | mean latent.

    python -m gsavatar.drive.compare --run out/demo/run_ours --drive encoder=out/demo/drive_test_encoder \
        predictor=out/demo/drive_test --out out/demo/latent_sources.png

Reads the latents each ``avatar-drive`` run wrote (``latents.npz``, one row per driven frame) for the
capture's test split, adds the training frames' mean latent (what a static avatar would show), and renders
the same frame from one held-out camera with each. Every panel is labelled with its PSNR inside the mask.
The default frame is the test frame where the encoder's render differs most from the mean latent's, so the
figure shows the appearance change the latent carries (``--frame`` picks another). Writes the PNG and a JSON
with the per-panel PSNRs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from gsavatar.data_schema import SchemaError
from gsavatar.drive.driver import DriveConfig, Driver, motion_inputs
from gsavatar.drive.metrics import load_ground_truth
from gsavatar.drive.motion import load_driving_motion
from gsavatar.metrics.image import psnr
from gsavatar.metrics.protocols import mask_bbox
from gsavatar.runs.latents import mean_train_latent
from gsavatar.runs.load import load_run
from gsavatar.utils.cli import run_reporting_errors
from gsavatar.utils.io import atomic_write_json, read_npz, write_image
from gsavatar.utils.outdir import claim_output_file, record_output_file


@dataclass
class CompareArgs:
    run: Path
    """Trained run (``avatar-train avatar`` + ``avatar-train predictor``)."""
    out: Path
    """PNG to write (a JSON with the numbers is written beside it)."""
    drive: list[str] = field(default_factory=list)
    """``label=DIR`` of ``avatar-drive --split test`` outputs whose latents to show (in this order)."""
    frame: int = -1
    """Index into the test sequence (-1: where the encoder and the mean latent differ most)."""
    camera: str = ""
    """Capture camera (empty: the first test camera)."""
    image_scale: float = 1.0
    """Image downscale factor."""
    force: bool = False
    """Replace an existing ``out`` (or its JSON) that is not a gsavatar figure (refused otherwise)."""


def body_box(mask: torch.Tensor, margin: float = 0.1) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` of ``mask > 0.5`` [H, W] widened by ``margin`` of its longer side + 2 px, clipped to
    the image; the whole image if the mask is empty. The crop of the figures that show a body."""
    box = mask_bbox(mask)
    H, W = mask.shape[-2:]
    if box is None:
        return 0, H, 0, W
    y0, y1, x0, x1 = box
    pad = int(margin * max(y1 - 1 - y0, x1 - 1 - x0)) + 2
    return max(0, y0 - pad), min(H, y1 + pad), max(0, x0 - pad), min(W, x1 + pad)


def _panel(img: torch.Tensor, height: int, text: str, min_width: int = 220) -> np.ndarray:
    """[h, w, 3] in [0, 1] -> uint8 panel scaled to ``height`` (nearest), padded to ``min_width``, caption above."""
    a = (img.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
    w = max(1, round(a.shape[1] * height / a.shape[0]))
    a = cv2.resize(a, (w, height), interpolation=cv2.INTER_NEAREST)
    if w < min_width:
        a = np.pad(a, ((0, 0), ((min_width - w) // 2, min_width - w - (min_width - w) // 2), (0, 0)))
    head = np.full((28, a.shape[1], 3), 255, np.uint8)
    cv2.putText(head, text, (4, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([head, a], 0)


@torch.no_grad()
def compare(args: CompareArgs) -> dict:
    claim_output_file(args.out, "figure", args.force, companions=(Path(args.out).with_suffix(".json"),))
    sources: dict[str, np.ndarray] = {}
    for spec in args.drive:
        label, sep, d = spec.partition("=")
        if not sep or not label:
            raise ValueError(f"--drive must be label=DIR, got {spec!r}")
        path = Path(d) / "latents.npz"
        if not path.exists():
            raise SchemaError(path, "", "missing: run avatar-drive with --out there first")
        z = read_npz(path, keys=("latents",))
        if "latents" not in z or z["latents"].ndim != 3 or z["latents"].dtype.kind not in "iuf":
            got = f"{z['latents'].dtype} array of shape {list(z['latents'].shape)}" if "latents" in z else "nothing"
            raise SchemaError(path, "latents", f"expected a real [T, A, L] array, got {got}")
        sources[label] = np.asarray(z["latents"], np.float32)  # [T, A, L]
    loaded = load_run(args.run)
    net, scene, tcfg = loaded.net, loaded.scene, loaded.config
    if not net.avatar.latent_in:
        raise ValueError(f"{args.run}: the avatar has no appearance latents to compare")
    cap = scene.capture
    cams = cap.splits["test"].cameras if "test" in cap.splits else cap.splits["train"].cameras
    cam = args.camera or cams[0]
    if cam not in cap.cameras:
        raise ValueError(f"camera must be one of {sorted(cap.cameras)}, got {cam!r}")
    d = Driver(
        args.run,
        DriveConfig(mode="encoder", capture_cameras=(cam,), image_scale=args.image_scale),
        loaded=loaded,
        predictor=None,
    )
    motion = load_driving_motion(cap.root, cap.rig, d.fps, split="test")
    T = motion.num_frames
    for label, lat in sources.items():
        if lat.shape[0] != T:
            raise ValueError(f"--drive {label}: {lat.shape[0]} frames of latents, the test split has {T}")
    mean = mean_train_latent(net, scene, d.device, tcfg.texture_source).cpu()
    dev = d.device
    d.use_capture_cameras(cap)

    def render(t: int, lat: torch.Tensor) -> torch.Tensor:
        x = d.check_inputs(motion_inputs(motion, t))
        return d.render(x, lat.to(dev))[0][cam]  # [H, W, 3]

    t = args.frame
    if t < 0:  # the frame whose appearance is furthest from the mean, judged by the encoder (or first source)
        ref = sources.get("encoder", next(iter(sources.values()))) if sources else None
        if ref is None:
            t = T // 2
        else:
            t = int(np.argmax([np.abs(ref[i] - mean.numpy()).mean() for i in range(T)]))
    if not 0 <= t < T:
        raise ValueError(f"frame must be in [0, {T}), got {t}")
    gt_img, gt_mask = load_ground_truth(cap, motion.gt.frames[t], [cam], args.image_scale, d.bg.cpu())[cam]
    m = (gt_mask > 0.5)[None, None].expand(1, 3, *gt_mask.shape)
    y0, y1, x0, x1 = body_box(gt_mask)  # every panel cropped to it: the body covers a tenth of the image
    H = max(384, 2 * (y1 - y0))
    panels = [_panel(gt_img[y0:y1, x0:x1], H, f"ground truth (frame {motion.gt.frames[t]})")]
    scores = {}
    for label, lat in [*((k, torch.from_numpy(v[t])) for k, v in sources.items()), ("mean latent", mean)]:
        img = render(t, lat)
        scores[label] = float(psnr(img.permute(2, 0, 1)[None], gt_img.permute(2, 0, 1)[None], mask=m)[0])
        panels.append(_panel(img[y0:y1, x0:x1], H, f"{label}: {scores[label]:.2f} dB"))
    out = Path(args.out)
    write_image(out, np.concatenate(panels, 1).astype(np.float32) / 255.0)
    info = {
        "run": str(args.run),
        "capture_frame": motion.gt.frames[t],
        "test_index": t,
        "camera": cam,
        "psnr_fg": scores,
        "figure": out.name,
    }
    atomic_write_json(out.with_suffix(".json"), info)
    record_output_file(out, "figure")
    print(
        f"latent sources at test frame {motion.gt.frames[t]} ({cam}): "
        + ", ".join(f"{k} {v:.2f} dB" for k, v in scores.items())
        + f" -> {out}"
    )
    return info


def main(argv: list[str] | None = None) -> int:
    import tyro

    args = tyro.cli(CompareArgs, args=argv, description=__doc__)
    return run_reporting_errors(lambda: compare(args))


if __name__ == "__main__":
    raise SystemExit(main())
