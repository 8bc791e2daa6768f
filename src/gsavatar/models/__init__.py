"""Gaussian avatar model: anchor MLPs, corrective bases, appearance encoder, PLY export.

- :class:`ModelConfig`, :func:`model_preset`, :func:`variant_config`, :class:`LearningRates`
- :class:`GaussianAvatar` -> :class:`AvatarOutput` (posed Gaussians per frame)
- :class:`AnchorMLPs` (one MLP per anchor, stacked weights)
- :class:`UVDecoder` (the nRFGCA-dagger baseline's convolutional UV decoder)
- :class:`AppearanceEncoder` (UV-texture CNN VAE), :func:`sample_at_uv`, :func:`kl_divergence`
- :func:`write_ply` / :func:`read_ply` / :func:`export_frame_ply` (standard 3DGS PLY)
"""

from gsavatar.models.avatar import AvatarOutput, GaussianAvatar
from gsavatar.models.config import (
    SH_C0,
    LearningRates,
    ModelConfig,
    model_preset,
    variant_config,
)
from gsavatar.models.encoder import (
    AppearanceEncoder,
    EncoderOutput,
    kl_divergence,
    mask_texture,
    reparameterize,
    sample_at_uv,
)
from gsavatar.models.mlp import AnchorMLPs, anchor_mlp_forward
from gsavatar.models.ply import PlyGaussians, export_frame_ply, ply_property_names, read_ply, write_ply
from gsavatar.models.uv_decoder import UVDecoder

__all__ = [
    "SH_C0",
    "AnchorMLPs",
    "AppearanceEncoder",
    "AvatarOutput",
    "EncoderOutput",
    "GaussianAvatar",
    "LearningRates",
    "ModelConfig",
    "PlyGaussians",
    "UVDecoder",
    "anchor_mlp_forward",
    "export_frame_ply",
    "kl_divergence",
    "mask_texture",
    "model_preset",
    "ply_property_names",
    "read_ply",
    "reparameterize",
    "sample_at_uv",
    "variant_config",
    "write_ply",
]
