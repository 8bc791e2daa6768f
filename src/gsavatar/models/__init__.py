"""Gaussian avatar model: pose heads, corrective bases, appearance encoder, PLY export.

- :class:`ModelConfig`, :func:`model_preset`, :data:`VARIANTS` / :func:`variant_config`, :class:`LearningRates`
- :class:`FrameBatch` -> :class:`AvatarNet` (avatar + encoder, the model's one input) -> :class:`NetOutput`
- :class:`GaussianAvatar` -> :class:`AvatarOutput` (posed Gaussians per frame)
- :class:`PoseHead` and :data:`POSE_HEADS` (the variants' pose-dependent part -> :class:`PoseDeltas`)
- :class:`AnchorMLPs` (one MLP per anchor, stacked weights)
- :class:`UVDecoder` (the nRFGCA-dagger baseline's convolutional UV decoder)
- :class:`AppearanceEncoder` (UV-texture CNN VAE), :func:`sample_at_uv`, :func:`reparameterize`
- :func:`write_ply` / :func:`read_ply` / :func:`export_frame_ply` (standard 3DGS PLY)
"""

from gsavatar.models.avatar import AvatarOutput, GaussianAvatar
from gsavatar.models.batch import FrameBatch
from gsavatar.models.config import (
    SH_C0,
    VARIANTS,
    LearningRates,
    ModelConfig,
    model_preset,
    variant_config,
)
from gsavatar.models.encoder import (
    AppearanceEncoder,
    EncoderOutput,
    mask_texture,
    reparameterize,
    sample_at_uv,
)
from gsavatar.models.mlp import AnchorMLPs, anchor_mlp_forward
from gsavatar.models.net import AvatarNet, NetOutput, build_net
from gsavatar.models.ply import PlyGaussians, export_frame_ply, ply_property_names, read_ply, write_ply
from gsavatar.models.pose_heads import POSE_HEADS, PoseDeltas, PoseHead
from gsavatar.models.uv_decoder import UVDecoder

__all__ = [
    "POSE_HEADS",
    "SH_C0",
    "VARIANTS",
    "AnchorMLPs",
    "AppearanceEncoder",
    "AvatarNet",
    "AvatarOutput",
    "EncoderOutput",
    "FrameBatch",
    "GaussianAvatar",
    "LearningRates",
    "ModelConfig",
    "NetOutput",
    "PlyGaussians",
    "PoseDeltas",
    "PoseHead",
    "UVDecoder",
    "anchor_mlp_forward",
    "build_net",
    "export_frame_ply",
    "mask_texture",
    "model_preset",
    "ply_property_names",
    "read_ply",
    "reparameterize",
    "sample_at_uv",
    "variant_config",
    "write_ply",
]
