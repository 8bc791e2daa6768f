"""The avatar trainer: loop, optimiser, checkpoints, DDP. Model math lives in gsavatar.models,
losses in gsavatar.train.losses, data in gsavatar.train.data."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader

from gsavatar.data_schema import SchemaError
from gsavatar.data_schema.dataset import dataset_fingerprint
from gsavatar.models.avatar import AvatarOutput, GaussianAvatar
from gsavatar.models.config import ModelConfig, model_preset, variant_config
from gsavatar.models.encoder import AppearanceEncoder, LatentNorm, sample_at_uv
from gsavatar.render import rasterize
from gsavatar.train import losses as L
from gsavatar.train.checkpoint import load_checkpoint, resume_hint, save_checkpoint
from gsavatar.train.config import TrainConfig, resolve, to_json
from gsavatar.train.data import PreparedScene, ViewDataset, load_scene
from gsavatar.train.sampler import StepBatchSampler, step_generator
from gsavatar.utils.cli import set_resume_hint
from gsavatar.utils.io import atomic_write_json, atomic_write_text
from gsavatar.utils.outdir import claim_output_dir


class NetOutput(NamedTuple):
    avatar: AvatarOutput
    mu: Tensor | None  # [B, L, h, w] posterior mean of the latent map (None without latents)
    logvar: Tensor | None  # [B, L, h, w]


class AvatarNet(nn.Module):
    """Avatar + appearance encoder behind one forward, so DDP sees every parameter."""

    def __init__(self, avatar: GaussianAvatar, encoder: AppearanceEncoder | None, anchor_uv: Tensor) -> None:
        super().__init__()
        self.avatar = avatar
        self.encoder = encoder
        self.register_buffer("anchor_uv", anchor_uv)  # [A, 2] OBJ convention
        self.latent_norm = None
        if encoder is not None and avatar.config.latent_norm:
            self.latent_norm = LatentNorm(anchor_uv.shape[0], encoder.latent_dim)

    def latents(self, texture: Tensor, eps: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """texture [B,3,S,S] -> per-anchor latents [B,A,L], mu, logvar. eps [B,L,h,w] = VAE noise (None: use mu).

        With ``latent_norm`` the latents are standardised per anchor and channel over frames (the running
        statistics update in training mode); every consumer (avatar, predictor targets, driving) sees that space.
        """
        enc = self.encoder(texture)
        z = enc.mu if eps is None else enc.mu + torch.exp(0.5 * enc.logvar) * eps
        lat = sample_at_uv(z, self.anchor_uv)
        if self.latent_norm is not None:
            lat = self.latent_norm(lat)
        return lat, enc.mu, enc.logvar

    def forward(self, pose: Tensor, root_rotation: Tensor, root_translation: Tensor, face: Tensor | None,
                texture: Tensor | None, eps: Tensor | None, sh_degree: int, correctives: bool,
                latents: Tensor | None = None) -> NetOutput:
        mu = logvar = None
        if self.encoder is not None and latents is None:
            latents, mu, logvar = self.latents(texture, eps)
        out = self.avatar(pose, root_rotation, root_translation, face, latents, sh_degree=sh_degree, correctives=correctives)
        return NetOutput(out, mu, logvar)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def model_config(cfg: TrainConfig) -> ModelConfig:
    return variant_config(model_preset(cfg.preset), cfg.variant)


def build_net(scene: PreparedScene, mcfg: ModelConfig, seed: int) -> AvatarNet:
    torch.manual_seed(seed)
    avatar = GaussianAvatar(scene.hierarchy, scene.masks, scene.capture.rig, scene.pca_local, scene.pca_global, mcfg,
                            face_dim=scene.face_dim, seed=seed)
    if avatar.config.input_norm:
        m = scene.capture.motion
        frames = scene.capture.splits["train"].frames
        face = torch.from_numpy(m.face[frames]).float() if m.face is not None else None
        avatar.set_input_stats(torch.from_numpy(m.pose[frames]).float(), face)
    encoder = AppearanceEncoder(latent_dim=mcfg.latent_dim) if mcfg.use_latent else None
    uv = torch.from_numpy(scene.hierarchy.anchors.uv).float()
    return AvatarNet(avatar, encoder, uv)


def render_views(out: AvatarOutput, viewmats: Tensor, Ks: Tensor, width: int, height: int, backgrounds: Tensor,
                 sh_degree: int, backend: str) -> tuple[Tensor, Tensor]:
    """Render item i of the batch from its own camera. -> colors [B,3,h,w], alphas [B,1,h,w]."""
    cols, alps = [], []
    for i in range(out.means.shape[0]):
        r = rasterize(out.means[i], out.quats[i], out.scales[i], out.opacities[i], out.sh[i], viewmats[i : i + 1],
                      Ks[i : i + 1], width, height, backgrounds=backgrounds[i : i + 1], sh_degree=sh_degree, backend=backend)
        cols.append(r.colors[0].permute(2, 0, 1))
        alps.append(r.alphas[0].permute(2, 0, 1))
    return torch.stack(cols), torch.stack(alps)


def trim_log(path: Path, step: int) -> None:
    """Drop the lines of a ``metrics.jsonl`` logged after ``step`` (a run resumed from an earlier checkpoint
    repeats those steps, so the log keeps one line per step). Torn last lines of a killed run go too."""
    if not path.exists():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if int(json.loads(line)["step"]) <= step:
                keep.append(line)
        except (ValueError, KeyError, TypeError, RecursionError):  # torn or foreign lines are dropped
            continue
    atomic_write_text(path, "".join(k + "\n" for k in keep))


def check_same_dataset(ckpt: Path, saved: dict, dataset: Path, dataset_id: str) -> None:
    """Refuse a checkpoint trained on another dataset than ``dataset`` (content id ``dataset_id``,
    :func:`gsavatar.data_schema.dataset.dataset_fingerprint`): another subject, or another preparation,
    now at the same path. Checkpoints written before ``dataset_id`` existed are compared by resolved path.
    Raises SchemaError naming ``ckpt`` and the field."""
    saved_id = saved.get("dataset_id")
    if saved_id is not None and saved_id != dataset_id:
        raise SchemaError(ckpt, "config.dataset_id", f"checkpoint was trained on another dataset (content "
                          f"{str(saved_id)[:12]}..., {dataset} now holds {dataset_id[:12]}...): the dataset was "
                          f"replaced or re-prepared; train a new run (another --out)")
    if saved_id is None:
        old = Path(saved["train"]["dataset"])
        if old.resolve() != Path(dataset).resolve():
            raise SchemaError(ckpt, "config.train.dataset", f"checkpoint has {str(old)!r}, this run has "
                              f"{str(dataset)!r}: it belongs to another configuration")


class Trainer:
    def __init__(self, cfg: TrainConfig, force_out: bool = False) -> None:
        """``force_out``: train into a non-empty ``cfg.out`` that is not a gsavatar run (refused otherwise)."""
        self.cfg = resolve(cfg)
        if self.cfg.deterministic:
            torch.set_num_threads(1)
            torch.use_deterministic_algorithms(True, warn_only=True)
        self.rank, self.world = int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))
        self.device = pick_device(self.cfg.device)
        if self.world > 1 and not torch.distributed.is_initialized():
            torch.distributed.init_process_group("nccl" if self.device.type == "cuda" else "gloo")
        self.out = Path(self.cfg.out)
        self.scene = load_scene(self.cfg.dataset)
        self.dataset_id = dataset_fingerprint(Path(self.cfg.dataset))
        if self.rank == 0:  # before the checkpoint is read or anything written; only rank 0 writes into the run
            claim_output_dir(self.out, "run", force_out)
        self.mcfg = model_config(self.cfg)
        self.net = build_net(self.scene, self.mcfg, self.cfg.seed).to(self.device)
        self.ddp = self.net
        if self.world > 1:
            self.ddp = nn.parallel.DistributedDataParallel(self.net, find_unused_parameters=True)
        groups = self.net.avatar.param_groups()
        for g in groups:  # CPU presets: faster corrective bases (TrainConfig.basis_lr_scale)
            if g["name"].endswith("_basis"):
                g["lr"] *= self.cfg.basis_lr_scale
        if self.net.encoder is not None:
            groups += self.net.encoder.param_groups()
        # fused: one kernel per parameter instead of ~10 passes over the ~15M basis scalars (55 -> 10 ms per
        # step on one CPU thread); the same update up to rounding.
        self.optim = torch.optim.AdamW(groups, eps=1e-15, betas=(0.9, 0.999),
                                       fused=self.device.type in ("cpu", "cuda"))
        self.lpips = None
        use_lpips = self.cfg.lpips == "on" or (self.cfg.lpips == "auto" and self.device.type == "cuda")
        if use_lpips and self.cfg.losses.lpips > 0:
            from gsavatar.metrics.lpips import LPIPS

            self.lpips = LPIPS(weights=self.cfg.lpips_weights).to(self.device)
        self.data = ViewDataset(self.scene, "train", image_scale=self.cfg.image_scale, with_texture=self.mcfg.use_latent,
                                texture_source=self.cfg.texture_source,
                                cache_bytes=int(self.cfg.cache_max_gb * 2**30) if self.cfg.cache_views else 0)
        self.neighbors = torch.from_numpy(self.scene.hierarchy.ctrl_neighbors).to(self.device)
        self.step = 0
        self.ckpt = self.out / "checkpoints" / "latest.pt"
        if self.ckpt.exists():
            self._resume()

    # ------------------------------------------------------------------ state
    def config_json(self) -> dict:
        return {"train": to_json(self.cfg), "model": self.mcfg.to_json() if hasattr(self.mcfg, "to_json") else
                {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.mcfg.__dict__.items()},
                "dataset_id": self.dataset_id}

    def _resume(self) -> None:
        # The dataset is identified by content (stage configs + file checksums), not by how its path was spelt;
        # checkpoints written before ``dataset_id`` existed are compared by resolved path.
        state = load_checkpoint(self.ckpt, self.config_json(), strict_config_keys=("model", "train.seed", "train.batch_size"))
        check_same_dataset(self.ckpt, state["config"], Path(self.cfg.dataset), self.dataset_id)
        self.net.load_state_dict(state["modules"]["net"])
        self.optim.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        if self.rank == 0:
            print(f"[train] resumed from {self.ckpt} at step {self.step}")

    def save(self) -> None:
        if self.rank != 0:
            return
        save_checkpoint(self.ckpt, step=self.step, config=self.config_json(), modules={"net": self.net},
                        optimizer=self.optim)
        set_resume_hint(resume_hint(self.ckpt, self.step))

    # ------------------------------------------------------------------ one step
    def sh_degree(self, step: int) -> int:
        return self.mcfg.sh_degree if step >= int(self.cfg.sh_increase_fraction * self.cfg.steps) else 0

    def backgrounds(self, gens: list[torch.Generator]) -> Tensor:
        if self.cfg.background == "random":
            return torch.stack([torch.rand(3, generator=g) for g in gens]).to(self.device)
        return torch.full((len(gens), 3), 1.0 if self.cfg.background == "white" else 0.0, device=self.device)

    def losses(self, batch: dict, step: int, positions: list[int]) -> tuple[Tensor, dict[str, float]]:
        dev = self.device
        b = {k: v.to(dev) for k, v in batch.items()}
        gens = [step_generator(self.cfg.seed, step, p) for p in positions]
        eps = None
        noise = self.cfg.vae_noise_step >= 0 and step >= self.cfg.vae_noise_step
        if self.net.encoder is not None and noise:
            S = b["texture"].shape[-1]
            h = S // self.net.encoder.downsample
            eps = torch.stack([torch.randn(self.mcfg.latent_dim, h, h, generator=g) for g in gens]).to(dev)
        face = b["face"] if b["face"].numel() else None
        sh = self.sh_degree(step)
        correctives = step >= self.cfg.correctives_step
        net_out = self.ddp(b["pose"], b["root_rotation"], b["root_translation"], face, b.get("texture"), eps, sh,
                           correctives)
        bg = self.backgrounds(gens)
        H, W = b["image"].shape[-2:]
        pred, alpha = render_views(net_out.avatar, b["viewmat"], b["K"], W, H, bg, sh, self.cfg.backend)
        gt = b["image"] * b["mask"] + bg[:, :, None, None] * (1 - b["mask"])
        w = self.cfg.losses
        terms = {
            "l1": L.l1_loss(pred, gt),
            "opac": L.opacity_loss(alpha, L.erode_mask(b["mask"], 3)),
            "scale": L.scale_loss(net_out.avatar.scales, self.mcfg.scale_max * 0.5),
            "cpt": L.cpt_smoothness_loss(net_out.avatar.ctrl_disp, self.neighbors),
        }
        if self.lpips is not None:
            terms["lpips"] = self.lpips(pred, gt).mean()
        if net_out.mu is not None and correctives and noise:
            # No KL while the correctives are off: the latent has no effect yet, so the KL would be the encoder's
            # only gradient and AdamW (scale invariant) would follow it at the full learning rate, whatever its
            # weight, collapsing the posterior to the prior before the avatar can use it. Measured on the small
            # capture (200 steps off of 1200): the anchor latents' spread over frames fell from 0.12 to 0.0036.
            terms["kl"] = L.kl_loss(net_out.mu, net_out.logvar)
        total, logs = L.total_loss(terms, w)
        return total, logs

    def train(self) -> dict:
        cfg = self.cfg
        sampler = StepBatchSampler(len(self.data), cfg.batch_size, cfg.seed, self.step, cfg.steps, self.rank, self.world)
        positions = sampler.positions()
        loader = DataLoader(self.data, batch_sampler=sampler, num_workers=cfg.num_workers,
                            persistent_workers=cfg.num_workers > 0)
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.out / "config.json", self.config_json())
        log_path = self.out / "metrics.jsonl"
        if self.rank == 0:
            trim_log(log_path, self.step)
        stop_at = cfg.steps if cfg.max_steps_this_run <= 0 else min(cfg.steps, self.step + cfg.max_steps_this_run)
        set_resume_hint(resume_hint(self.ckpt, self.step))
        t0, n0 = time.perf_counter(), self.step
        last: dict[str, float] = {}
        self.net.train()
        for batch in loader:
            if self.step >= stop_at:
                break
            loss, logs = self.losses(batch, self.step, positions)
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self.optim.step()
            self.step += 1
            if self.world > 1:  # log the global-batch mean, like a single process would
                keys = sorted(logs)
                t = torch.tensor([logs[k] for k in keys], dtype=torch.float64)
                torch.distributed.all_reduce(t)
                logs = {k: float(v) / self.world for k, v in zip(keys, t)}
            last = logs
            if self.rank == 0 and (self.step % cfg.log_every == 0 or self.step == stop_at):
                rate = (self.step - n0) / (time.perf_counter() - t0)
                line = {"step": self.step, **{k: round(v, 6) for k, v in logs.items()}, "steps_per_s": round(rate, 3)}
                with open(log_path, "a") as f:
                    f.write(json.dumps(line) + "\n")
                print(f"[train] step {self.step}/{cfg.steps} loss {logs['total']:.4f} l1 {logs['l1']:.4f} "
                      f"({rate:.2f} steps/s)", flush=True)
            if self.step % cfg.checkpoint_every == 0 or self.step == stop_at:
                self.save()
        seconds = time.perf_counter() - t0
        if self.rank == 0 and self.step > n0:
            self._record_timing(self.step - n0, seconds)
        return {"step": self.step, **last, "seconds": seconds}

    def _record_timing(self, steps: int, seconds: float) -> None:
        """Accumulate training time over the invocations of a run in ``timing.json`` (steps, seconds, steps/s,
        threads), for the results table. Steps repeated after a resume count again (they were paid again)."""
        path = self.out / "timing.json"
        prev = {"steps": 0, "seconds": 0.0, "invocations": 0}
        try:
            got = json.loads(path.read_text()) if path.exists() else {}
            got = {**prev, **got}
            prev = {"steps": int(got["steps"]), "seconds": float(got["seconds"]), "invocations": int(got["invocations"])}
        except (ValueError, TypeError, KeyError, RecursionError):
            pass  # a torn (killed run) or foreign file: start the tally again
        tot_steps, tot_s = prev["steps"] + steps, prev["seconds"] + seconds
        atomic_write_json(path, {"steps": tot_steps, "seconds": round(tot_s, 2),
                                 "steps_per_s": round(tot_steps / max(tot_s, 1e-9), 4),
                                 "invocations": int(prev["invocations"]) + 1, "threads": torch.get_num_threads(),
                                 "device": str(self.device)})
