"""The avatar trainer: loop, optimiser, checkpoints, DDP. Model math lives in gsavatar.models (the net
in gsavatar.models.net), losses in gsavatar.train.losses, data in gsavatar.train.data, the run's config
and checkpoint format in gsavatar.runs."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader

from gsavatar.data_schema.dataset import dataset_fingerprint
from gsavatar.data_schema.prepared import load_scene
from gsavatar.metrics.lpips import load_lpips
from gsavatar.models.batch import FrameBatch
from gsavatar.models.config import LearningRates, ModelConfig
from gsavatar.models.kernels import path_report
from gsavatar.models.net import build_net
from gsavatar.runs.checkpoint import (
    check_same_dataset,
    load_checkpoint,
    load_optimizer_by_group_name,
    resume_hint,
    save_checkpoint,
)
from gsavatar.runs.config import TrainConfig, resolve, to_json, upgrade_run_json
from gsavatar.runs.load import pick_device
from gsavatar.runs.views import render_views
from gsavatar.train import losses as L
from gsavatar.train.data import ViewDataset
from gsavatar.train.sampler import StepBatchSampler, step_generator
from gsavatar.utils.cli import set_resume_hint
from gsavatar.utils.io import atomic_write_json, atomic_write_text
from gsavatar.utils.jsonio import dataclass_defaults
from gsavatar.utils.outdir import claim_output_dir
from gsavatar.utils.provenance import code_version


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
        self.mcfg = self.cfg.model  # resolved: the preset's with the variant, or the run's own
        self.net = build_net(self.scene, self.mcfg, self.cfg.seed).to(self.device)
        self.ddp = self.net
        if self.world > 1:
            self.ddp = nn.parallel.DistributedDataParallel(self.net, find_unused_parameters=True)
        lrs = LearningRates()
        groups = self.net.avatar.param_groups(lrs)
        for g in groups:  # CPU presets: faster corrective bases (TrainConfig.basis_lr_scale)
            if g["name"].endswith("_basis"):
                g["lr"] *= self.cfg.schedule.basis_lr_scale
        if self.net.encoder is not None:
            groups += self.net.encoder.param_groups(lrs)
        # fused: one kernel per parameter instead of ~10 passes over the ~15M basis scalars (55 -> 10 ms per
        # step on one CPU thread); the same update up to rounding.
        self.optim = torch.optim.AdamW(groups, eps=1e-15, betas=(0.9, 0.999), fused=self.device.type in ("cpu", "cuda"))
        # the loss: --lpips auto = on when training on CUDA (TrainConfig.lpips); none with a zero weight
        self.lpips = load_lpips(
            self.cfg.lpips if self.cfg.losses.lpips > 0 else "off",
            self.device,
            self.cfg.lpips_weights,
            auto_on=self.device.type == "cuda",
        ).net
        self.data = ViewDataset(
            self.scene,
            "train",
            image_scale=self.cfg.schedule.image_scale,
            with_texture=self.mcfg.use_latent,
            texture_source=self.cfg.texture_source,
            cache_bytes=int(self.cfg.cache_max_gb * 2**30) if self.cfg.cache_views else 0,
        )
        self.neighbors = torch.from_numpy(self.scene.hierarchy.ctrl_neighbors).to(self.device)
        self.step = 0
        self.ckpt = self.out / "checkpoints" / "latest.pt"
        if self.ckpt.exists():
            self._resume()

    # ------------------------------------------------------------------ state
    def config_json(self) -> dict:
        return {"train": to_json(self.cfg), "model": self.mcfg.to_json(), "dataset_id": self.dataset_id}

    def _resume(self) -> None:
        # The dataset is identified by content (stage configs + file checksums), not by how its path was spelt;
        # checkpoints written before ``dataset_id`` existed are compared by resolved path.
        state = load_checkpoint(
            self.ckpt,
            self.config_json(),
            strict_config_keys=("model", "train.seed", "train.schedule.batch_size"),
            upgrade=upgrade_run_json,
            defaults={"model": dataclass_defaults(ModelConfig)},
        )
        check_same_dataset(self.ckpt, state["config"], Path(self.cfg.dataset), self.dataset_id)
        self.net.load_state_dict(state["modules"]["net"])
        load_optimizer_by_group_name(self.optim, state["optimizer"], self.ckpt)  # groups matched by name
        self.step = int(state["step"])
        if self.rank == 0:
            print(f"[train] resumed from {self.ckpt} at step {self.step}")

    def save(self) -> None:
        if self.rank != 0:
            return
        save_checkpoint(
            self.ckpt, step=self.step, config=self.config_json(), modules={"net": self.net}, optimizer=self.optim
        )

    # ------------------------------------------------------------------ one step
    def sh_degree(self, step: int) -> int:
        sch = self.cfg.schedule
        return self.mcfg.sh_degree if step >= int(sch.sh_increase_fraction * sch.steps) else 0

    def backgrounds(self, gens: list[torch.Generator]) -> Tensor:
        if self.cfg.background == "random":
            return torch.stack([torch.rand(3, generator=g) for g in gens]).to(self.device)
        return torch.full((len(gens), 3), 1.0 if self.cfg.background == "white" else 0.0, device=self.device)

    def losses(self, batch: dict, step: int, positions: list[int]) -> tuple[Tensor, dict[str, float]]:
        dev = self.device
        b = {k: v.to(dev) for k, v in batch.items()}
        gens = [step_generator(self.cfg.seed, step, p) for p in positions]
        eps = None
        noise = self.cfg.schedule.vae_noise_step != "never" and step >= self.cfg.schedule.vae_noise_step
        if self.net.encoder is not None and noise:
            S = b["texture"].shape[-1]
            h = S // self.net.encoder.downsample
            eps = torch.stack([torch.randn(self.mcfg.latent_dim, h, h, generator=g) for g in gens]).to(dev)
        sh = self.sh_degree(step)
        correctives = step >= self.cfg.schedule.correctives_step
        net_out = self.ddp(FrameBatch.from_dict(b), sh_degree=sh, correctives=correctives, eps=eps)
        bg = self.backgrounds(gens)
        H, W = b["image"].shape[-2:]
        pred, alpha = render_views(net_out.avatar, b["viewmat"], b["K"], W, H, bg, sh, self.cfg.backend)
        gt = b["image"] * b["mask"] + bg[:, :, None, None] * (1 - b["mask"])
        w = self.cfg.losses
        terms = {
            "l1": L.l1_loss(pred, gt),
            "opac": L.opacity_loss(alpha, L.min_filter_mask(b["mask"], 3)),
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
        cfg, sch = self.cfg, self.cfg.schedule
        sampler = StepBatchSampler(
            len(self.data), sch.batch_size, cfg.seed, self.step, sch.steps, self.rank, self.world
        )
        positions = sampler.positions()
        loader = DataLoader(
            self.data, batch_sampler=sampler, num_workers=cfg.num_workers, persistent_workers=cfg.num_workers > 0
        )
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.out / "config.json", self.config_json())
        log_path = self.out / "metrics.jsonl"
        if self.rank == 0:
            trim_log(log_path, self.step)
        stop_at = sch.steps if cfg.max_steps_this_run is None else min(sch.steps, self.step + cfg.max_steps_this_run)
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
                print(
                    f"[train] step {self.step}/{sch.steps} loss {logs['total']:.4f} l1 {logs['l1']:.4f} "
                    f"({rate:.2f} steps/s)",
                    flush=True,
                )
            if self.step % sch.checkpoint_every == 0 or self.step == stop_at:
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
        commits: set[str] = set()
        try:
            got = json.loads(path.read_text()) if path.exists() else {}
            got = {**prev, **got}
            prev = {
                "steps": int(got["steps"]),
                "seconds": float(got["seconds"]),
                "invocations": int(got["invocations"]),
            }
            commits = {c for c in got.get("commits", []) if isinstance(c, str)}
        except (ValueError, TypeError, KeyError, RecursionError):
            pass  # a torn (killed run) or foreign file: start the tally again
        tot_steps, tot_s = prev["steps"] + steps, prev["seconds"] + seconds
        atomic_write_json(
            path,
            {
                "steps": tot_steps,
                "seconds": round(tot_s, 2),
                "steps_per_s": round(tot_steps / max(tot_s, 1e-9), 4),
                "invocations": int(prev["invocations"]) + 1,
                "threads": torch.get_num_threads(),
                "device": str(self.device),
                # which path each fast kernel took in this process so far (models/kernels.py: compiled or torch, why)
                "kernel_paths": path_report(),
                # the code that trained it: the last invocation's commit, and every commit that added steps
                "code": code_version(),
                "commits": sorted(commits | {code_version()["commit"]} - {None}),
            },
        )
