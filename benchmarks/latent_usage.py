"""Does the avatar use its appearance latents? Short training runs, one recipe change each.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/latent_usage.py --dataset out/demo/dataset \
        --out /tmp/lat --name no_center --no-center --steps 600 --correctives-step 100

Trains ``ours`` (``small`` model) on the dataset with the CPU recipe (``gsavatar.models.config.CPU_RECIPE``,
``Schedule.basis_lr_scale``/``vae_noise_step`` of the preset) minus the named change (the model is passed as
``TrainConfig.model``, the same as ``avatar-train avatar --model.*`` flags), then prints one JSON
line: ``latent_gain_db`` (PSNR inside the mask on held-out cameras of test frames, encoder latents minus the
training mean latent), the frame-dependence ratio (avatar colour std over training frames / ground truth's),
the PSNRs and the seconds. Results of our runs are in docs/train.md ("A recipe for the CPU budget").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--correctives-step", type=int, default=100)
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--no-input-norm", action="store_true", help="raw MLP pose/face inputs")
    ap.add_argument("--no-center", action="store_true", help="coefficients MLP(x), not MLP(x) - MLP(x_ref)")
    ap.add_argument("--no-latent-norm", action="store_true", help="raw encoder latents")
    ap.add_argument("--paper-model", action="store_true", help="all three above (the paper's model)")
    ap.add_argument("--anchor-sh0", action="store_true", help="also a per-anchor colour basis (ModelConfig.anchor_sh0)")
    ap.add_argument(
        "--latent-sh0", action="store_true", help="also a latent -> colour map per anchor (ModelConfig.latent_sh0)"
    )
    ap.add_argument(
        "--anchor-lr-scale",
        type=float,
        default=None,
        help="learning-rate scale of the per-anchor colour basis (default: the other bases')",
    )
    ap.add_argument(
        "--mlp-init", choices=("linear", "he"), default=None, help="anchor-MLP init (default: the recipe's)"
    )
    ap.add_argument("--basis-lr-scale", type=float, default=0.0, help="0 = the preset's (10)")
    ap.add_argument(
        "--vae-noise-step", type=int, default=-2, help="-2 = the preset's (never); else VAE noise + KL from"
    )
    a = ap.parse_args()

    from gsavatar.models.config import CPU_RECIPE, model_preset
    from gsavatar.runs.config import Schedule, TrainConfig
    from gsavatar.runs.load import LoadedRun
    from gsavatar.train.runs import evaluate_run
    from gsavatar.train.trainer import Trainer

    off = {
        "input_norm": a.no_input_norm or a.paper_model,
        "center_correctives": a.no_center or a.paper_model,
        "latent_norm": a.no_latent_norm or a.paper_model,
    }
    recipe = {k: (not off[k]) if k in off else v for k, v in CPU_RECIPE.items()}  # the CPU recipe minus the change
    if a.anchor_sh0:
        recipe["anchor_sh0"] = True
    if a.latent_sh0:
        recipe["latent_sh0"] = True
    if a.mlp_init is not None:
        recipe["mlp_init"] = a.mlp_init
    cfg = TrainConfig(
        dataset=a.dataset,
        out=a.out / a.name,
        preset="small",
        model=model_preset("small").replace(**recipe),  # the small model with the recipe above, no module patched
        schedule=Schedule(
            steps=a.steps,
            correctives_step=a.correctives_step,
            image_scale=a.image_scale,
            checkpoint_every=10**9,
            basis_lr_scale=a.basis_lr_scale or None,
            vae_noise_step={-2: None, -1: "never"}.get(a.vae_noise_step, a.vae_noise_step),
        ),
        lpips="off",
        log_every=100,
    )
    tr = Trainer(cfg)
    if a.anchor_lr_scale is not None:
        for g in tr.optim.param_groups:
            if g["name"] == "sh0_anchor_basis":
                g["lr"] *= a.anchor_lr_scale / tr.cfg.schedule.basis_lr_scale
    t = time.perf_counter()
    tr.train()
    seconds = time.perf_counter() - t
    res = evaluate_run(tr.out, 8, loaded=LoadedRun(tr.net, tr.scene, tr.cfg, tr.step))
    print(
        json.dumps(
            {
                "name": a.name,
                "recipe": recipe,
                "basis_lr_scale": tr.cfg.schedule.basis_lr_scale,
                "anchor_lr_scale": a.anchor_lr_scale,
                "vae_noise_step": tr.cfg.schedule.vae_noise_step,
                "steps": a.steps,
                "latent_gain_db": round(res["latent_gain_db"], 4),
                "frame_dependence": round(res.get("frame_dependence", {}).get("ratio", float("nan")), 4),
                "test_psnr_fg": round(res["test_frames_heldout_cams"]["psnr_fg"], 3),
                "train_psnr_fg": round(res["train_frames_heldout_cams"]["psnr_fg"], 3),
                "seconds": round(seconds),
            }
        )
    )


if __name__ == "__main__":
    main()
