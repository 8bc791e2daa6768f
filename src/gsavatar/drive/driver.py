"""Drive a trained avatar with a motion: appearance latents per frame + renders, one frame at a time.

Streaming API (live driving)::

    d = Driver(run, DriveConfig(mode="predictor"))
    d.start(first)                  # FrameInputs of frame 0: initialises the predictor state
    for x in frames:                # frame 0 first, then 1, 2, ...
        out = d.step(x)             # DriveFrame(latents [A, L], images {cam: [H, W, 3]}, alphas, t)

``drive(motion)`` / ``frames(motion)`` are exactly ``start`` + one ``step`` per frame, so batch ==
streaming.

The mode (``DriveConfig.mode``) names a latent source of :data:`gsavatar.drive.sources.LATENT_SOURCES`
(where each frame's appearance latents come from: encoder, predictor with zero / pose / encoder
initialisation, re-initialisation every K frames); the driver builds it once and asks it for the latents
of each frame. Models without appearance latents (MMLPs-dagger) render from pose alone in any mode.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from gsavatar.data_schema import Capture, SchemaError
from gsavatar.data_schema.dataset import read_dataset_json
from gsavatar.data_schema.prepared import ProjectedTextures
from gsavatar.data_schema.views import scaled_camera
from gsavatar.drive.motion import DrivingMotion
from gsavatar.drive.sources import DriveMode, LatentSource, PoseOnly, SourceContext, source_class
from gsavatar.models.batch import FrameBatch
from gsavatar.runs.config import model_config
from gsavatar.runs.load import LoadedRun, load_run, predictor_from_checkpoint, run_predictor_path
from gsavatar.runs.views import orbit_cameras, render_views


@dataclass
class DriveConfig:
    """How to drive: where the appearance latents come from and which cameras render."""

    mode: DriveMode = "predictor"
    """Where each frame's appearance latents come from: a latent source of
    :data:`gsavatar.drive.sources.LATENT_SOURCES` (each described by its class; docs/drive.md)."""
    reinit_every: int = 30
    """K of mode ``reinit``: frames between encoder re-initialisations (paper: 30)."""
    cameras: Literal["capture", "orbit"] = "capture"
    """``capture``: calibrated cameras of the driving capture (else the run's capture); ``orbit``: a ring
    of virtual cameras around the avatar's first-frame position."""
    capture_cameras: tuple[str, ...] = ()
    """Names of the capture cameras to render (empty: the capture's test cameras, else its train cameras)."""
    image_scale: float = 1.0
    """Capture cameras: image downscale factor (1 = calibrated resolution)."""
    orbit_views: int = 4
    """Orbit: number of cameras evenly spaced on the ring."""
    orbit_size: int = 256
    """Orbit: square image size, pixels."""
    orbit_radius: float = 2.6
    """Orbit: ring radius around the avatar, metres."""
    orbit_height: float = 0.2
    """Orbit: camera height above the avatar's centre, metres."""
    video_fps: float = 0.0
    """Frame rate written into the mp4 (0: the motion's frame rate after resampling)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour (RGB in [0, 1]); ground truth is composited onto it for metrics."""
    textures: Path | None = None
    """Prepared dataset (``avatar-prep all``) of the driving capture, for the encoder modes; default: the
    run's dataset when the driving capture is the run's own capture."""
    device: str = "auto"
    """``auto`` (CUDA if available), ``cpu`` or ``cuda[:i]``."""

    def __post_init__(self) -> None:
        source_class(self.mode)  # raises for an unregistered mode
        if self.reinit_every < 1:
            raise ValueError(f"reinit_every must be >= 1, got {self.reinit_every}")
        if self.cameras not in ("capture", "orbit"):
            raise ValueError(f"cameras must be 'capture' or 'orbit', got {self.cameras!r}")
        if not self.image_scale > 0:
            raise ValueError(f"image_scale must be > 0, got {self.image_scale}")
        if self.orbit_views < 1 or self.orbit_size < 8:
            raise ValueError(f"orbit_views must be >= 1 and orbit_size >= 8, got {self.orbit_views}, {self.orbit_size}")
        if len(self.background) != 3 or not all(0.0 <= float(c) <= 1.0 for c in self.background):
            raise ValueError(f"background must be 3 values in [0, 1], got {self.background!r}")
        if self.video_fps < 0:
            raise ValueError(f"video_fps must be >= 0, got {self.video_fps}")


class FrameInputs(NamedTuple):
    pose: Tensor
    """Pose parameters, radians.  # [P]"""
    root_rotation: Tensor
    """Axis-angle.  # [3]"""
    root_translation: Tensor
    """Metres.  # [3]"""
    face: Tensor | None = None
    """Face embedding (None: zeros when the model has one).  # [E]"""
    texture: Tensor | None = None
    """Projected UV texture in [0, 1], needed by the encoder modes on init frames.  # [3, S, S]"""

    def batch(self, latents: Tensor | None) -> FrameBatch:
        """This frame as a batch of one for the net, with given latents ``[A, L]`` (None: the model has none)."""
        return FrameBatch(
            self.pose[None],
            self.root_rotation[None],
            self.root_translation[None],
            None if self.face is None else self.face[None],
            None,
            None if latents is None else latents[None],
        )


class View(NamedTuple):
    name: str
    viewmat: Tensor
    """cam_from_world.  # [4, 4]"""
    K: Tensor
    """Pinhole intrinsics, pixels.  # [3, 3]"""
    width: int
    height: int


class DriveFrame(NamedTuple):
    latents: Tensor
    """Appearance latents of this frame (cpu; [A, 0] for models without latents).  # [A, L]"""
    images: dict[str, Tensor]
    """Render per camera, RGB in [0, 1] on ``background`` (cpu float32).  # {cam: [H, W, 3]}"""
    alphas: dict[str, Tensor]
    """Accumulated opacity per camera (cpu float32).  # {cam: [H, W]}"""
    t: int
    """Index of the frame since ``start``."""


def load_predictor_for(run: Path, device: str | torch.device = "cpu"):
    """The run's trained appearance predictor (``RUN/predictor/latest.pt`` of ``avatar-train predictor``),
    or None when the run has none."""
    ckpt = run_predictor_path(run)
    if not ckpt.exists():
        return None
    return predictor_from_checkpoint(ckpt, device)


def capture_views(capture: Capture, names: tuple[str, ...] | list[str], image_scale: float) -> list[View]:
    """Calibrated (undistorted, resized) views of ``names`` (empty: test cameras, else train)."""
    if not names:
        names = (capture.splits["test"] if "test" in capture.splits else capture.splits["train"]).cameras
    unknown = [n for n in names if n not in capture.cameras]
    if unknown:
        raise ValueError(
            f"capture_cameras: unknown camera {unknown[0]!r}; {capture.root} has {sorted(capture.cameras)}"
        )
    views = []
    for n in names:
        g = scaled_camera(capture.cameras[n], image_scale)
        views.append(View(n, torch.from_numpy(g.cam_from_world), torch.from_numpy(g.K), g.width, g.height))
    return views


def motion_inputs(motion: DrivingMotion, t: int, texture: Tensor | None = None) -> FrameInputs:
    """Frame ``t`` of a driving motion as :class:`FrameInputs`."""
    if not 0 <= t < motion.num_frames:
        raise ValueError(f"t must be in [0, {motion.num_frames}), got {t}")
    f = torch.from_numpy
    face = None if motion.face is None else f(np.ascontiguousarray(motion.face[t]))
    return FrameInputs(
        f(np.ascontiguousarray(motion.pose[t])),
        f(np.ascontiguousarray(motion.root_rotation[t])),
        f(np.ascontiguousarray(motion.root_translation[t])),
        face,
        texture,
    )


def texture_source(motion: DrivingMotion, scene, textures: Path | None) -> Callable[[int], Tensor]:
    """Driving frame t -> projected UV texture [3, S, S] of its ground-truth capture frame."""
    if motion.gt is None:
        raise ValueError(
            "the encoder modes need projected UV textures of the driving frames: drive with a capture "
            "directory (at its own frame rate, or an integer multiple of it)"
        )
    cap_root = Path(motion.gt.capture.root).resolve()
    ds = Path(textures) if textures is not None else None
    if ds is None:
        if cap_root != Path(scene.capture.root).resolve():
            raise ValueError(f"no projected textures for {cap_root}: run `avatar-prep all` on it and pass textures=")
        ds = Path(scene.dataset)
    meta_cap = read_dataset_json(ds).get("capture")
    if not meta_cap or Path(meta_cap).resolve() != cap_root:
        raise SchemaError(ds / "dataset.json", "capture", f"is {meta_cap!r}, not the driving capture {cap_root}")
    textures = ProjectedTextures(ds)
    frames = motion.gt.frames

    def get(t: int) -> Tensor:
        return torch.from_numpy(textures.get(frames[t])).permute(2, 0, 1).contiguous()

    return get


class Driver:
    """Streaming avatar driver (module docstring).

    Args:
        run: run directory of ``avatar-train avatar``.
        config: :class:`DriveConfig`.
        loaded: the run as :func:`gsavatar.runs.load_run` returns it, to skip reloading.
        predictor: the appearance predictor (``init_state``/``step``/``initial_latents``); ``"auto"``
            loads the run's when the mode's source needs one; None: none (only modes without a
            predictor, or models without latents).
        camera_capture: capture whose calibrated cameras render (default: the run's capture).
    """

    def __init__(
        self,
        run: str | Path,
        config: DriveConfig | None = None,
        *,
        loaded: LoadedRun | None = None,
        predictor="auto",
        camera_capture: Capture | None = None,
    ) -> None:
        self.config = cfg = config if config is not None else DriveConfig()
        self.run = Path(run)
        self.loaded = loaded if loaded is not None else load_run(self.run, cfg.device)
        net, scene, tcfg, _ = self.loaded
        self.net, self.scene, self.train_cfg = net.eval(), scene, tcfg
        self.device = next(net.parameters()).device
        self.sh_degree = model_config(tcfg).sh_degree
        self.backend = tcfg.backend
        av = net.avatar
        self.num_anchors, self.pose_dim, self.face_dim = av.num_anchors, av.pose_dim, av.config.face_dim
        self.latent_dim = av.latent_in
        self.has_latents = self.latent_dim > 0
        kind = source_class(cfg.mode) if self.has_latents else PoseOnly
        if kind.needs_texture and net.encoder is None:
            raise ValueError(f"mode {cfg.mode!r} needs the run's appearance encoder; this run has none")
        if isinstance(predictor, str):
            if predictor != "auto":
                raise ValueError(f"predictor must be a predictor object, None or 'auto', got {predictor!r}")
            predictor = load_predictor_for(self.run) if kind.needs_predictor else None
        if predictor is not None and hasattr(predictor, "to"):
            predictor = predictor.to(self.device).eval()
        self.predictor = predictor
        if kind.needs_predictor and predictor is None:
            raise ValueError(
                f"mode {cfg.mode!r} needs a trained appearance predictor in {self.run / 'predictor'}; "
                "train one first or use mode 'encoder' (needs textures)"
            )
        self.source: LatentSource = kind(
            SourceContext(cfg, self.encode, predictor, self.num_anchors, self.latent_dim, self.device)
        )
        """The latent source of ``config.mode`` (:class:`~gsavatar.drive.sources.PoseOnly` without latents)."""
        self.fps = float(getattr(predictor, "fps", 0.0) or scene.capture.fps)
        """Frame rate the predictor was trained at (driving motions are resampled to it)."""
        self.camera_capture = camera_capture or scene.capture
        self.views: list[View] = []
        if cfg.cameras == "capture":
            self.views = capture_views(self.camera_capture, cfg.capture_cameras, cfg.image_scale)
        self.bg = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.t = -1

    def use_capture_cameras(self, capture: Capture) -> None:
        """Render ``capture``'s calibrated cameras (``config.capture_cameras``, default its test cameras)."""
        self.camera_capture = capture
        if self.config.cameras == "capture":
            self.views = capture_views(capture, self.config.capture_cameras, self.config.image_scale)

    def with_mode(self, mode: DriveMode) -> Driver:
        """A driver of another mode sharing this one's run, predictor and cameras (fresh state)."""
        return Driver(
            self.run,
            dataclasses.replace(self.config, mode=mode),
            loaded=self.loaded,
            predictor=self.predictor,
            camera_capture=self.camera_capture,
        )

    # ------------------------------------------------------------------ latents
    @property
    def needs_textures(self) -> bool:
        """Whether the mode reads projected textures (``FrameInputs.texture``) on some frames."""
        return self.source.needs_texture

    def texture_needed_at(self, t: int) -> bool:
        """Whether :meth:`step` of frame ``t`` (and :meth:`start` for t = 0) reads ``FrameInputs.texture``."""
        return self.source.texture_needed_at(t)

    @torch.no_grad()
    def encode(self, texture: Tensor | None) -> Tensor:
        """Encoder latents (posterior mean) of a projected texture [3, S, S] -> [A, L]."""
        if texture is None:
            raise ValueError(f"mode {self.config.mode!r}: FrameInputs.texture is required on this frame")
        if texture.ndim != 3 or texture.shape[0] != 3:
            raise ValueError(f"texture must be [3, S, S], got {list(texture.shape)}")
        return self.net.latents(texture[None].to(self.device, torch.float32), None)[0][0]

    def check_inputs(self, x: FrameInputs) -> FrameInputs:
        """Validated inputs as float32 on the driver's device (a missing face is zeros when the model has one),
        as :meth:`render` takes them; raises ValueError naming the field."""
        if not isinstance(x, FrameInputs):
            raise ValueError(f"inputs must be FrameInputs, got {type(x).__name__}")
        dev = self.device
        t = lambda v: torch.as_tensor(v, dtype=torch.float32).to(dev)  # noqa: E731
        pose, rr, rt = t(x.pose), t(x.root_rotation), t(x.root_translation)
        for name, v, n in (("pose", pose, self.pose_dim), ("root_rotation", rr, 3), ("root_translation", rt, 3)):
            if v.shape != (n,):
                raise ValueError(f"{name} must be [{n}], got {list(v.shape)}")
            if not torch.isfinite(v).all():
                raise ValueError(f"{name} contains NaN/Inf")
        face = None
        if self.face_dim:
            face = torch.zeros(self.face_dim, device=dev) if x.face is None else t(x.face)
            if face.shape != (self.face_dim,):
                raise ValueError(f"face must be [{self.face_dim}], got {list(face.shape)}")
        return FrameInputs(pose, rr, rt, face, x.texture)

    # ------------------------------------------------------------------ streaming
    @torch.no_grad()
    def start(self, first: FrameInputs) -> None:
        """Initialise a new sequence from frame 0's inputs (the next :meth:`step` must be frame 0)."""
        x = self.check_inputs(first)
        self.t = 0
        if self.config.cameras == "orbit":
            lat = torch.zeros(self.num_anchors, self.latent_dim, device=self.device) if self.has_latents else None
            out = self.net(x.batch(lat), sh_degree=self.sh_degree)
            center = out.avatar.means[0].mean(0).cpu().double().numpy()
            s = self.config.orbit_size
            vms, Ks = orbit_cameras(
                center, self.config.orbit_radius, self.config.orbit_height, self.config.orbit_views, s, s
            )
            self.views = [View(f"orbit{i:02d}", vms[i], Ks[i], s, s) for i in range(len(vms))]
        self.source.init(x)

    @torch.no_grad()
    def render(self, x: FrameInputs, latents: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Render inputs checked by :meth:`check_inputs` with latents [A, L] from every view
        -> ({cam: [H,W,3]}, {cam: [H,W]}) on cpu."""
        out = self.net(x.batch(latents.to(self.device) if self.has_latents else None), sh_degree=self.sh_degree)
        images, alphas = {}, {}
        for v in self.views:
            col, alp = render_views(
                out.avatar,
                v.viewmat[None].to(self.device),
                v.K[None].to(self.device),
                v.width,
                v.height,
                self.bg[None],
                self.sh_degree,
                self.backend,
            )
            images[v.name] = col[0].clamp(0, 1).permute(1, 2, 0).float().cpu()
            alphas[v.name] = alp[0, 0].float().cpu()
        return images, alphas

    @torch.no_grad()
    def step(self, inputs: FrameInputs, render: bool = True) -> DriveFrame:
        """Latents and renders of the next frame (frame 0 first, right after :meth:`start`).
        ``render=False``: latents only (empty image dicts)."""
        if self.t < 0:
            raise ValueError("call start(first_frame_inputs) before step()")
        x = self.check_inputs(inputs)
        lat = self.source.next(x, self.t)
        images, alphas = self.render(x, lat) if render else ({}, {})
        frame = DriveFrame(lat.detach().float().cpu(), images, alphas, self.t)
        self.t += 1
        return frame

    # ------------------------------------------------------------------ batch
    def frames(self, motion: DrivingMotion, textures: Callable[[int], Tensor] | None = None) -> Iterator[DriveFrame]:
        """Generator over a whole motion: ``start`` + ``step`` per frame. ``textures(t) -> [3,S,S]``
        (default: :func:`texture_source` when the mode needs them)."""
        if self.needs_textures and textures is None:
            textures = texture_source(motion, self.scene, self.config.textures)
        if motion.num_frames < 1:
            raise ValueError("motion has no frames")
        if motion.pose.shape[1] != self.pose_dim:
            raise ValueError(f"motion.pose must be [T, {self.pose_dim}], got {list(motion.pose.shape)}")
        get = lambda t: motion_inputs(motion, t, textures(t) if self.texture_needed_at(t) else None)  # noqa: E731
        first = get(0)
        self.start(first)
        for t in range(motion.num_frames):
            yield self.step(first if t == 0 else get(t))

    def drive(self, motion: DrivingMotion, textures: Callable[[int], Tensor] | None = None) -> list[DriveFrame]:
        """All frames of ``motion`` (see :meth:`frames`)."""
        return list(self.frames(motion, textures))
