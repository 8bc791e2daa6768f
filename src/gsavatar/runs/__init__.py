"""A trained run on disk and what every consumer does with it: its configuration and checkpoint
format, loading it back (:func:`load_run` -> :class:`LoadedRun`), rendering views of the avatar and
latent statistics. Sits below ``train`` (which writes runs) and ``drive`` (which reads them), so
neither imports the other (docs/architecture.md)."""

from gsavatar.runs.config import LossWeights, TrainConfig, model_config, resolve
from gsavatar.runs.latents import mean_train_latent
from gsavatar.runs.load import LoadedRun, load_run, pick_device, predictor_from_checkpoint, run_predictor_path
from gsavatar.runs.views import orbit_cameras, render_views

__all__ = [
    "LoadedRun",
    "LossWeights",
    "TrainConfig",
    "load_run",
    "mean_train_latent",
    "model_config",
    "orbit_cameras",
    "pick_device",
    "predictor_from_checkpoint",
    "render_views",
    "resolve",
    "run_predictor_path",
]
