"""Whole-run operations: train then evaluate, export a PLY, render a turntable (loading a run back is
:func:`gsavatar.runs.load_run`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from gsavatar.metrics.lpips import load_lpips
from gsavatar.metrics.protocols import PROTOCOLS, load_ag_lpips
from gsavatar.metrics.temporal import frame_dependence
from gsavatar.models.batch import FrameBatch
from gsavatar.models.config import SH_C0
from gsavatar.models.encoder import sample_at_uv
from gsavatar.models.net import AvatarNet
from gsavatar.models.ply import export_frame_ply
from gsavatar.runs.config import TrainConfig, check_train_config, model_config
from gsavatar.runs.latents import mean_train_latent
from gsavatar.runs.load import LoadedRun, load_run
from gsavatar.runs.views import orbit_cameras, render_views
from gsavatar.train.data import ViewDataset
from gsavatar.train.evaluate import evaluate_views, select_frames
from gsavatar.train.trainer import Trainer
from gsavatar.utils.io import atomic_write_json


def train_and_evaluate(cfg: TrainConfig, evaluate: bool = True, force_out: bool = False) -> dict:
    """Train (resuming) then evaluate; ``force_out``: accept a non-empty ``cfg.out`` that is not a gsavatar run."""
    check_train_config(cfg)
    tr = Trainer(cfg, force_out=force_out)
    summary = tr.train()
    if tr.rank == 0:
        print(f"[train] {summary['step']} steps in {summary['seconds']:.0f}s this run")
    if evaluate and tr.rank == 0 and tr.step >= tr.cfg.schedule.steps:
        res = evaluate_run(tr.out, tr.cfg.eval_frames, loaded=LoadedRun(tr.net, tr.scene, tr.cfg, tr.step))
        print(json.dumps(res, indent=1))
        return res
    return summary


def evaluate_run(run: Path, eval_frames: int = 8, loaded: LoadedRun | None = None, ag_lpips: str = "auto") -> dict:
    """Held-out cameras of training frames ("novel view") and held-out frames ("novel pose"), encoder latents.

    ``loaded``: the run as a live trainer holds it, to skip reloading the checkpoint. ``ag_lpips``: the
    ``ag`` protocol's LPIPS (:func:`gsavatar.metrics.protocols.load_ag_lpips`; ``auto`` = on CUDA).
    """
    run = Path(run)
    net, scene, cfg, _ = loaded if loaded is not None else load_run(run)
    dev = next(net.parameters()).device
    lp = load_lpips(cfg.lpips, dev, cfg.lpips_weights)  # evaluation: the metric unless --lpips off
    ag_nets, ag_names = load_ag_lpips(dev, "off" if cfg.lpips == "off" else ag_lpips)
    splits = scene.capture.splits
    sh = model_config(cfg).sh_degree
    results = {}
    test_cams = splits["test"].cameras if "test" in splits else splits["train"].cameras
    sets = {"train_frames_heldout_cams": (select_frames(splits["train"].frames, eval_frames), test_cams)}
    if "test" in splits:
        sets["test_frames_heldout_cams"] = (select_frames(splits["test"].frames, eval_frames), test_cams)
    for name, (frames, cams) in sets.items():
        data = ViewDataset(
            scene,
            "train",
            cameras=cams,
            frames=frames,
            image_scale=cfg.schedule.image_scale,
            with_texture=net.encoder is not None,
            texture_source=cfg.texture_source,
        )
        results[name] = evaluate_views(
            net, data, dev, sh, cfg.backend, lpips=lp.net, save_dir=run / "eval" / name, ag_lpips=ag_nets
        )
    if net.encoder is not None and "test" in splits:
        # How much the appearance latent buys: the same held-out views with every frame's latents replaced by
        # the training frames' mean latent. ~0 dB means the avatar ignores its latents.
        mean_lat = mean_train_latent(net, scene, dev, cfg.texture_source)
        frames, cams = sets["test_frames_heldout_cams"]
        data = ViewDataset(
            scene, "train", cameras=cams, frames=frames, image_scale=cfg.schedule.image_scale, with_texture=False
        )
        r = evaluate_views(net, data, dev, sh, cfg.backend, latents_fn=lambda f: mean_lat)
        results["test_frames_heldout_cams_mean_latent"] = r
        results["latent_gain_db"] = results["test_frames_heldout_cams"]["psnr_fg"] - r["psnr_fg"]
    fd = run_frame_dependence(net, scene, cfg.texture_source)
    if fd is not None:
        results["frame_dependence"] = fd
    results["lpips_net"] = lp.name
    results["protocols"] = dict(PROTOCOLS)
    results["ag_lpips_nets"] = ag_names
    results["variant"] = cfg.variant
    atomic_write_json(run / "eval" / "metrics.json", results)
    return results


@torch.no_grad()
def run_frame_dependence(net: AvatarNet, scene, texture_source: str = "projected", num_frames: int = 24) -> dict | None:
    """Per-Gaussian colour (SH band 0) spread over training frames vs the ground-truth albedo's at the
    Gaussians' UVs (:func:`gsavatar.metrics.temporal.frame_dependence`); None without ``gt/textures``."""
    uv = scene.hierarchy.gaussians.uv
    frames = select_frames(scene.capture.splits["train"].frames, num_frames)
    gt_dir = scene.capture.root / "gt" / "textures"
    if uv is None or not all((gt_dir / f"{f:08d}.png").exists() for f in frames):
        return None
    dev = next(net.parameters()).device
    net.eval()
    data = ViewDataset(
        scene,
        "train",
        cameras=scene.capture.splits["train"].cameras[:1],
        frames=frames,
        with_texture=net.encoder is not None,
        texture_source=texture_source,
    )
    uv_t = torch.from_numpy(np.asarray(uv)).float()
    pred, gt = [], []
    for f in frames:
        b = {k: v[None].to(dev) for k, v in data.frame_inputs(f).items()}
        out = net(FrameBatch.from_dict(b), sh_degree=0).avatar
        pred.append((out.sh[0, :, 0] * SH_C0 + 0.5).clamp(0, 1).cpu())  # [G, 3]
        tex = torch.from_numpy(data.gt_texture(f)).permute(2, 0, 1)[None]  # [1, 3, S, S]
        gt.append(sample_at_uv(tex, uv_t)[0])  # [G, 3]
    gt_t = torch.stack(gt)
    outside_face = (
        gt_t.abs().amax(dim=(0, 2)) > 0
    ).double()  # the face (blanked, explained by the face input) is left out
    return frame_dependence(torch.stack(pred), gt_t, outside_face) | {"frames": len(frames)}


@torch.no_grad()
def posed_output(net: AvatarNet, scene, frame: int, sh_degree: int):
    data = ViewDataset(
        scene,
        "train",
        cameras=scene.capture.splits["train"].cameras[:1],
        frames=[frame],
        with_texture=net.encoder is not None,
    )
    b = {k: (v[None] if torch.is_tensor(v) else v) for k, v in data.frame_inputs(frame).items()}
    dev = next(net.parameters()).device
    b = {k: v.to(dev) for k, v in b.items()}
    return net(FrameBatch.from_dict(b), sh_degree=sh_degree).avatar


def export_ply(run: Path, frame: int, out: Path) -> None:
    net, scene, cfg, _ = load_run(run)
    if not 0 <= frame < scene.capture.num_frames:
        raise ValueError(f"frame must be in [0, {scene.capture.num_frames}), got {frame}")
    export_frame_ply(out, posed_output(net, scene, frame, model_config(cfg).sh_degree), frame=0)


@torch.no_grad()
def render_turntable(
    run: Path, out_mp4: Path, frame: int = 0, n_views: int = 48, size: int = 256, fps: int = 24
) -> Path:
    """Orbit around the posed avatar of ``frame`` and write an mp4 (imageio-ffmpeg)."""
    import imageio.v2 as imageio

    net, scene, cfg, _ = load_run(run)
    sh = model_config(cfg).sh_degree
    out = posed_output(net, scene, frame, sh)
    center = out.means[0].mean(0).cpu().numpy()
    vms, Ks = orbit_cameras(center, 2.6, 0.2, n_views, size, size)
    frames = []
    for i in range(n_views):
        col, _ = render_views(out, vms[i : i + 1], Ks[i : i + 1], size, size, torch.ones(1, 3), sh, cfg.backend)
        frames.append((col[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8))
    out_mp4 = Path(out_mp4)
    out_mp4.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_mp4.with_name(f".{out_mp4.stem}.tmp.mp4")
    imageio.mimwrite(tmp, frames, fps=fps, macro_block_size=1)
    tmp.replace(out_mp4)
    return out_mp4
