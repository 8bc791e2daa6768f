"""Every model variant of a tiny avatar, and fingerprints of its outputs (tests/models/test_pose_heads.py).

Uses only the avatar's public API of before and after the pose-head refactor, so the same code fingerprints
both: ``python tests/avatar_variants.py OUT.json`` writes the fingerprints of the code it runs against;
``tests/models/data/variants_before_pose_heads.json`` holds those of the code before the refactor (commit
0fdce94), computed in float64.
"""

from __future__ import annotations

import json
import sys
import typing

import numpy as np
import torch

from gsavatar.models import GaussianAvatar, model_preset, variant_config
from gsavatar.models.config import VariantName
from gsavatar.prep.localize import build_localization
from gsavatar.prep.pca import fit_pose_pca
from gsavatar.prep.sample_points import build_hierarchy
from prep_fixtures import arm_rig, arm_template

VARIANT_NAMES = tuple(typing.get_args(VariantName))
CALLS = {"train": (True, True, 1), "eval": (False, True, 1), "bias_only": (True, False, 1), "sh0": (True, True, 0)}
"""name -> (training mode, correctives, sh_degree): the PCA modes, the pose head and the SH bands each path uses."""
FACE_DIM = 3


def legacy_name(name: str) -> str:
    """Parameter name as before the pose head held the pose network (``pose_head.mlp.*`` was ``mlp.*``)."""
    return name.removeprefix("pose_head.")


def build_parts(n_gaussians: int = 300):
    rig, t = arm_rig(), arm_template()
    h = build_hierarchy(t, n_anchors=16, n_control=60, n_gaussians=n_gaussians, seed=0, min_candidates=2000)
    masks = build_localization(h, rig, t.face_uv_mask)
    poses = np.random.default_rng(0).normal(size=(60, rig.pose_dim)) * 0.3
    return rig, h, masks, fit_pose_pca(poses, rig, 2, "local"), fit_pose_pca(poses, rig, 3, "global")


def make_variant(
    parts, name: str, center_correctives: bool = True, dtype: torch.dtype = torch.float32
) -> GaussianAvatar:
    """The variant ``name`` of the tiny preset with non-zero corrective bases / decoder (seeded)."""
    rig, h, masks, pl, pg = parts
    # the model as it was when the fingerprints below were stored: without the later opt-in latent colour map
    base = model_preset("tiny", uv_decoder_size=32, uv_decoder_channels=32).replace(latent_sh0=False)
    if not center_correctives:
        base = base.replace(input_norm=False, center_correctives=False, latent_norm=False)
    torch.manual_seed(3)  # the UV decoder's init draws from the global generator
    av = GaussianAvatar(h, masks, rig, pl, pg, variant_config(base, name), face_dim=FACE_DIM, seed=1)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for n, p in av.named_parameters():  # bases and the UV decoder (its last conv starts at zero)
            if not legacy_name(n).startswith("mlp") and not n.endswith("_bias"):
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    gi = torch.Generator().manual_seed(7)
    if av.config.input_norm:
        av.set_input_stats(torch.randn(30, rig.pose_dim, generator=gi) * 0.3, torch.randn(30, FACE_DIM, generator=gi))
    return av.to(dtype)


def make_inputs(parts, B: int = 2, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, ...]:
    """(pose [B, P], root_rotation [B, 3], root_translation [B, 3], face [B, E], latents [B, A, 16])."""
    rig, h = parts[0], parts[1]
    g = torch.Generator().manual_seed(9)
    x = (
        torch.randn(B, rig.pose_dim, generator=g) * 0.3,
        torch.randn(B, 3, generator=g) * 0.3,
        torch.randn(B, 3, generator=g),
        torch.randn(B, FACE_DIM, generator=g),
        torch.randn(B, h.num_anchors, 16, generator=g),
    )
    return tuple(t.to(dtype) for t in x)


def output_weights(out, seed: int = 11) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {f: torch.rand(getattr(out, f).shape, generator=g, dtype=torch.float64) for f in out._fields}


def fingerprints(parts=None) -> dict[str, float]:
    """Weighted sums (fixed random weights) of every output field and of every parameter's gradient of a
    weighted-sum loss, per variant and call (:data:`CALLS`), in float64."""
    parts = parts if parts is not None else build_parts()
    inputs = make_inputs(parts, dtype=torch.float64)
    res: dict[str, float] = {}
    for name in VARIANT_NAMES:
        av = make_variant(parts, name, dtype=torch.float64)
        for call, (training, correctives, sh) in CALLS.items():
            av.train(training)
            av.zero_grad(set_to_none=True)
            out = av(*inputs, sh_degree=sh, correctives=correctives)
            w = output_weights(out)
            loss = sum((getattr(out, f) * w[f]).sum() for f in out._fields)
            loss.backward()
            for f in out._fields:
                res[f"{name}/{call}/out/{f}"] = float((getattr(out, f).detach() * w[f]).sum())
            g = torch.Generator().manual_seed(13)
            for n, p in sorted(av.named_parameters(), key=lambda np_: legacy_name(np_[0])):
                if p.grad is not None:
                    res[f"{name}/{call}/grad/{legacy_name(n)}"] = float(
                        (p.grad * torch.rand(p.shape, generator=g, dtype=torch.float64)).sum()
                    )
    return res


if __name__ == "__main__":
    with open(sys.argv[1], "w") as f:
        json.dump(fingerprints(), f, indent=0, sort_keys=True)
