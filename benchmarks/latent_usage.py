"""Does the avatar use its appearance latents? Short training runs with VAE variations.

    PYTHONPATH=src .venv/bin/python benchmarks/latent_usage.py --dataset out/demo/dataset --out /tmp/lat \
        --name cap6 --logvar-max -6 --steps 500 --correctives-step 100 --image-scale 0.5

Trains ``ours`` on the dataset with the given changes, then prints one JSON line: ``latent_gain_db``
(PSNR inside the mask on held-out cameras of test frames, encoder latents minus the training mean
latent; see ``avatar-train eval``), the PSNRs, and the spread of the per-anchor latents over training
frames (std over frames, mean over anchors and channels) against their mean magnitude. Results of
our runs are in docs/train.md.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def latent_spread(net, scene, every: int = 8) -> tuple[float, float]:
    """(std over training frames, mean |.|) of the encoder's per-anchor latents."""
    from gsavatar.train.data import ViewDataset

    data = ViewDataset(scene, "train", cameras=scene.capture.splits["train"].cameras[:1])
    net.eval()
    with torch.no_grad():
        lats = torch.stack([net.latents(data.frame_inputs(f)["texture"][None], None)[0][0] for f in data.frames[::every]])
    return float(lats.std(0).mean()), float(lats.abs().mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--correctives-step", type=int, default=100)
    ap.add_argument("--image-scale", type=float, default=0.5)
    ap.add_argument("--kl", type=float, default=1e-6, help="KL weight (paper 1e-6)")
    ap.add_argument("--logvar-max", type=float, default=None, help="upper clamp of the encoder's log-variance")
    ap.add_argument("--no-noise", action="store_true", help="latents = mu in training too (no reparameterisation)")
    ap.add_argument("--basis-lr-scale", type=float, default=1.0, help="multiply the corrective bases' learning rates")
    a = ap.parse_args()

    import gsavatar.models.encoder as enc
    from gsavatar.train.config import TrainConfig
    from gsavatar.train.losses import LossWeights
    from gsavatar.train.runs import evaluate_run
    from gsavatar.train.trainer import Trainer

    if a.logvar_max is not None:  # read at call time by the encoder's forward
        enc.LOGVAR_RANGE = (enc.LOGVAR_RANGE[0], a.logvar_max)
    cfg = TrainConfig(dataset=a.dataset, out=a.out / a.name, preset="small", steps=a.steps,
                      correctives_step=a.correctives_step, image_scale=a.image_scale, lpips="off",
                      checkpoint_every=10**9, log_every=100, losses=LossWeights(kl=a.kl))
    tr = Trainer(cfg)
    if a.no_noise:
        latents = tr.net.latents
        tr.net.latents = lambda texture, eps: latents(texture, None)
    for g in tr.optim.param_groups:
        if g["name"].endswith("_basis"):
            g["lr"] *= a.basis_lr_scale
    t = time.perf_counter()
    tr.train()
    res = evaluate_run(tr.out, 4, loaded=(tr.net, tr.scene, tr.cfg))
    spread, mag = latent_spread(tr.net, tr.scene)
    print(json.dumps({"name": a.name, "latent_gain_db": round(res["latent_gain_db"], 4),
                      "test_psnr_fg": round(res["test_frames_heldout_cams"]["psnr_fg"], 3),
                      "train_psnr_fg": round(res["train_frames_heldout_cams"]["psnr_fg"], 3),
                      "latent_spread": round(spread, 5), "latent_abs": round(mag, 5),
                      "seconds": round(time.perf_counter() - t)}))


if __name__ == "__main__":
    main()
