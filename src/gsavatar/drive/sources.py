"""Latent sources: where the appearance latents [A, L] of each driven frame come from (the drive modes).

A drive mode is one :class:`LatentSource` subclass. Its class statement names the mode and so registers it
in :data:`LATENT_SOURCES`, the one table from which :data:`DriveMode` (the ``avatar-drive --mode`` choices),
``DriveConfig.mode`` validation and the ramp-up study's modes are derived::

    class HoldFirst(LatentSource, mode="hold_first"):
        \"\"\"The encoder's latents of frame 0, held for the whole sequence.\"\"\"

        needs_texture = True

        def texture_needed_at(self, t: int) -> bool:
            return t == 0

        def init(self, x: FrameInputs) -> None:
            self.first = self.ctx.encode(x.texture)

        def next(self, x: FrameInputs, t: int) -> Tensor:
            return self.first

The :class:`~gsavatar.drive.driver.Driver` builds the source of ``DriveConfig.mode`` once, checks what it
declares it needs (``needs_texture``: the run's appearance encoder and projected textures on the frames of
``texture_needed_at``; ``needs_predictor``: a trained appearance predictor), calls :meth:`LatentSource.init`
with frame 0's inputs in ``start`` and :meth:`LatentSource.next` with each frame's inputs in ``step``.
Inputs are the driver's checked :class:`~gsavatar.drive.driver.FrameInputs` (tensors on the driver's device;
``texture`` only on the frames ``texture_needed_at`` names); calls run under ``torch.no_grad``.

The predictor-driven modes follow :meth:`gsavatar.models.predictor.AppearancePredictor.rollout` exactly
(tested bit for bit). Models without appearance latents (MMLPs-dagger) get :class:`PoseOnly` in any mode.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar, Literal, NamedTuple

import torch
from torch import Tensor

if TYPE_CHECKING:  # annotations only: driver.py imports this module
    from gsavatar.drive.driver import DriveConfig, FrameInputs


class SourceContext(NamedTuple):
    """What a latent source may use, given by the driver."""

    config: DriveConfig
    """The drive's configuration (e.g. ``reinit_every``)."""
    encode: Callable[[Tensor | None], Tensor]
    """Projected UV texture [3, S, S] in [0, 1] -> the run's encoder latents (posterior mean) [A, L];
    raises ValueError for a missing texture."""
    predictor: Any
    """The appearance predictor (``init_state``/``step``/``initial_latents``, an
    :class:`~gsavatar.models.predictor.AppearancePredictor`) or None when none is loaded."""
    num_anchors: int
    """A."""
    latent_dim: int
    """L (0: the model has no appearance latents)."""
    device: torch.device

    def zeros(self) -> Tensor:
        """Zero latents.  # [A, L]"""
        return torch.zeros(self.num_anchors, self.latent_dim, device=self.device)


LATENT_SOURCES: dict[str, type[LatentSource]] = {}
"""Drive mode name -> latent source class, in registration order (the order of ``--mode``'s choices)."""


class LatentSource:
    """Where each frame's appearance latents come from. Subclass with ``mode="name"`` to register a drive mode.

    Args:
        ctx: the driver's :class:`SourceContext`. The driver has checked the needs declared below before
            building a source, so ``ctx.predictor`` is not None when ``needs_predictor`` is set.
    """

    mode: ClassVar[str]
    """The drive mode's name (``DriveConfig.mode``), set by the class statement's ``mode=``."""
    needs_texture: ClassVar[bool] = False
    """Reads ``FrameInputs.texture`` (projected UV textures, through the run's appearance encoder)."""
    needs_predictor: ClassVar[bool] = False
    """Steps the run's trained appearance predictor."""
    ramp_up: ClassVar[bool] = False
    """One of the initialisations the ramp-up study (``--ramp-up``) compares by default."""
    in_viewer: ClassVar[bool] = True
    """Offered in the live viewer's latent menu."""
    matches_encoder: ClassVar[bool] = False
    """Its latents are the encoder's of every frame, the ramp-up's target (latent error 0 by construction)."""

    def __init_subclass__(cls, mode: str | None = None, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if mode is None:  # an abstract or unregistered source
            return
        if not mode.isidentifier():
            raise ValueError(f"drive mode names must be identifiers, got {mode!r}")
        if mode in LATENT_SOURCES:
            raise ValueError(f"drive mode {mode!r} is already registered by {LATENT_SOURCES[mode].__qualname__}")
        cls.mode = mode
        LATENT_SOURCES[mode] = cls

    def __init__(self, ctx: SourceContext) -> None:
        self.ctx = ctx

    def texture_needed_at(self, t: int) -> bool:
        """Whether :meth:`next` of frame ``t`` (and :meth:`init` for t = 0) reads ``FrameInputs.texture``."""
        return self.needs_texture

    def init(self, x: FrameInputs) -> None:
        """Start a new sequence from frame 0's inputs (the next :meth:`next` is frame 0)."""

    def next(self, x: FrameInputs, t: int) -> Tensor:
        """Latents of frame ``t`` (0, 1, 2, ... in order; advances any state).  -> [A, L]"""
        raise NotImplementedError


def source_class(mode: str) -> type[LatentSource]:
    """The registered latent source of drive mode ``mode``."""
    if mode not in LATENT_SOURCES:
        raise ValueError(f"mode must be one of {'/'.join(LATENT_SOURCES)}, got {mode!r}")
    return LATENT_SOURCES[mode]


def ramp_up_modes() -> tuple[str, ...]:
    """The modes the ramp-up study compares by default, in table order."""
    return tuple(m for m, cls in LATENT_SOURCES.items() if cls.ramp_up)


# --------------------------------------------------------------------------- the modes
class PoseOnly(LatentSource):
    """Models without appearance latents (MMLPs-dagger): empty latents [A, 0], in any mode (not registered)."""

    def next(self, x: FrameInputs, t: int) -> Tensor:
        return torch.zeros(self.ctx.num_anchors, 0, device=self.ctx.device)


class Predicted(LatentSource):
    """The predictor steps every frame from its state; subclasses choose frame 0's previous latents."""

    needs_predictor = True

    def initial_latents(self, x: FrameInputs) -> Tensor:
        """Previous latents of frame 0 (the predictor's initial state).  -> [A, L]"""
        raise NotImplementedError

    def init(self, x: FrameInputs) -> None:
        self.first = self.initial_latents(x)
        self.state = self.ctx.predictor.init_state(x.pose, x.root_rotation, x.root_translation, self.first)

    def next(self, x: FrameInputs, t: int) -> Tensor:
        lat, self.state = self.ctx.predictor.step(self.state, x.pose, x.root_rotation, x.root_translation)
        return lat


class ZeroInit(Predicted, mode="predictor"):
    """Previous latents of frame 0 = "zeros" (the paper's fallback without textures; ramps up over the first
    frames), every frame predicted. Zero in the predictor's standardised latent space, i.e. its training-mean
    latent (``PredictorConfig.zero_context``; raw zeros for predictors trained before it existed)."""

    ramp_up = True

    def initial_latents(self, x: FrameInputs) -> Tensor:
        zero = getattr(self.ctx.predictor, "zero_latents", None)
        return zero().to(self.ctx.device) if zero is not None else self.ctx.zeros()


class NeedsInitialNet(LatentSource):
    """A source that reads the predictor's pose-conditioned InitialLatentNet: refuses a predictor without a trained
    one when it is built."""

    def __init__(self, ctx: SourceContext) -> None:
        p = ctx.predictor
        if not hasattr(p, "initial_latents") or not bool(getattr(p, "initial_ready", True)):
            raise ValueError(f"mode {self.mode!r} needs a predictor with a trained InitialLatentNet")
        super().__init__(ctx)


class PoseInit(NeedsInitialNet, Predicted, mode="pose_init"):
    """Previous latents of frame 0 = the predictor's pose-conditioned InitialLatentNet (beyond the paper: its
    future-work item), every frame predicted."""

    ramp_up = True

    def initial_latents(self, x: FrameInputs) -> Tensor:
        return self.ctx.predictor.initial_latents(x.pose[None])[0]


class EncoderInit(Predicted, mode="predictor_encoder_init"):
    """Frame 0 = the encoder's latents of its projected texture (teacher-forced), prediction from frame 1
    (the paper's table 1 "Ours")."""

    needs_texture = True
    ramp_up = True

    def texture_needed_at(self, t: int) -> bool:
        return t == 0

    def initial_latents(self, x: FrameInputs) -> Tensor:
        return self.ctx.encode(x.texture)

    def next(self, x: FrameInputs, t: int) -> Tensor:
        return self.first if t == 0 else super().next(x, t)


class Reinit(EncoderInit, mode="reinit"):
    """As ``predictor_encoder_init``, and at every ``t % reinit_every == 0`` the previous latents are first
    replaced by the encoder's latents of frame t (paper: "re-init. 30")."""

    ramp_up = False  # the first reinit_every frames are predictor_encoder_init's

    def texture_needed_at(self, t: int) -> bool:
        return t % self.ctx.config.reinit_every == 0

    def next(self, x: FrameInputs, t: int) -> Tensor:
        if t > 0 and self.texture_needed_at(t):
            self.state = self.state._replace(latents=self.ctx.encode(x.texture).to(self.state.latents))
        return super().next(x, t)


class TrainMean(LatentSource, mode="train_mean"):
    """The training frames' mean latent every frame, as the run's predictor stores it (what an avatar without
    appearance dynamics shows; the baseline the predictor's recovery is measured against). No texture."""

    needs_predictor = True
    in_viewer = False  # the viewer has its own mean latent (the encoder's, without a predictor)

    def next(self, x: FrameInputs, t: int) -> Tensor:
        return self.ctx.predictor.latent_mean.to(self.ctx.device)


class PoseRegression(NeedsInitialNet, mode="pose_regression"):
    """Every frame's latents from the current pose alone: the predictor's InitialLatentNet applied frame by frame,
    with no pose window and no fed-back latents. The ablation without any memory of the motion (the no-history
    predictor, N_b = 1, still carries the past in the latents it feeds back)."""

    needs_predictor = True

    def next(self, x: FrameInputs, t: int) -> Tensor:
        return self.ctx.predictor.initial_latents(x.pose[None])[0].to(self.ctx.device)


class Encoder(LatentSource, mode="encoder"):
    """The encoder's latents every frame (upper bound; needs textures every frame)."""

    needs_texture = True
    ramp_up = True
    matches_encoder = True

    def next(self, x: FrameInputs, t: int) -> Tensor:
        return self.ctx.encode(x.texture)


DriveMode = Literal[tuple(LATENT_SOURCES)]  # type: ignore[valid-type]
"""Names of the drive modes defined above (``avatar-drive --mode``). Sources registered later (a user's
module) drive through the Python API; ``DriveConfig`` accepts every registered name."""
