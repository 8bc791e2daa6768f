"""Image-quality metrics used for evaluation and as training losses.

* :func:`psnr`, :func:`ssim` (Wang et al. 2004, skimage-compatible settings), per image ``[B]``.
* :class:`LPIPS` (AlexNet / VGG16, vanilla LPIPS v0.1 or ST-LPIPS weights), per image ``[B]``;
  always report its ``lpips_name``. Commands build it with :func:`load_lpips` (``--lpips auto|on|off``).
"""

from .image import gaussian_kernel1d, mse, psnr, psnr_from_mse, ssim, ssim_map
from .temporal import frame_dependence
from .lpips import (
    LPIPS,
    LoadedLPIPS,
    LPIPSMode,
    LPIPSWeightsError,
    convert_official_lpips,
    load_lpips,
    official_lpips_state_dict,
)

__all__ = [
    "LPIPS",
    "LPIPSMode",
    "LPIPSWeightsError",
    "LoadedLPIPS",
    "convert_official_lpips",
    "frame_dependence",
    "gaussian_kernel1d",
    "load_lpips",
    "mse",
    "official_lpips_state_dict",
    "psnr",
    "psnr_from_mse",
    "ssim",
    "ssim_map",
]
