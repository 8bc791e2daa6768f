"""Live Gaussian generation: one driven frame -> Gaussians a splat viewer draws (no rasterization).

    g = LiveGaussians(driver)                    # a Driver of any mode (its cameras are not used)
    g.start(x0)                                  # FrameInputs of the first frame
    frame = g.next(x1, eye=camera_position)      # ViewerGaussians: centers, covariances, rgbs, opacities

Per frame: the latent source's step (the appearance predictor in the predictor modes), the avatar's
forward pass, the world covariances ``R diag(s)^2 R^T`` from its scales and quaternions, and its SH
evaluated to one RGB per Gaussian for the direction from ``eye`` (the viewer's camera centre) to each
Gaussian (``sh0_only``: band 0 only, view independent). :attr:`LiveGaussians.timings` accumulates the
seconds of each part (``benchmarks/bench_drive_gaussians.py`` prints them).

Besides the registered drive modes (:data:`gsavatar.drive.sources.LATENT_SOURCES`) the viewer offers
:data:`MEAN_LATENT`: the training frames' mean encoder latent every frame (a static appearance).
"""

from __future__ import annotations

import time
from collections import defaultdict
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

from gsavatar.data_schema import SchemaError
from gsavatar.drive.driver import Driver, FrameInputs, motion_inputs, texture_source
from gsavatar.drive.motion import load_driving_motion
from gsavatar.drive.sources import LATENT_SOURCES
from gsavatar.models.ply import export_frame_ply
from gsavatar.render.sh import SH_C0, eval_sh_colors
from gsavatar.runs.latents import mean_train_latent
from gsavatar.utils.compiled import CACHE
from gsavatar.utils.outdir import claim_output_dir
from gsavatar.utils.progress import progress_bar

MEAN_LATENT = "mean_latent"
"""Viewer-only latent source: the training frames' mean encoder latent, every frame."""


class ViewerGaussians(NamedTuple):
    """One frame's Gaussians as splat viewers take them (float32 numpy)."""

    centers: np.ndarray
    """World centres, metres.  # [N, 3]"""
    covariances: np.ndarray
    """World covariances, metres^2.  # [N, 3, 3]"""
    rgbs: np.ndarray
    """Colour in [0, 1] for the viewing direction.  # [N, 3]"""
    opacities: np.ndarray
    """Activated opacity in (0, 1).  # [N, 1]"""


def covariances_from(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances ``M M^T`` with ``M = R(q) diag(s)``.

    Args:
        quats: Tensor  # [N, 4] unit quaternions wxyz
        scales: Tensor  # [N, 3] standard deviations along the local axes

    Returns:
        Tensor  # [N, 3, 3] symmetric positive semi-definite
    """
    w, x, y, z = quats.unbind(-1)
    sx, sy, sz = scales.unbind(-1)
    # rows of R (wxyz, unit), each column j scaled by s_j
    m = torch.stack(
        [
            (1 - 2 * (y * y + z * z)) * sx,
            2 * (x * y - w * z) * sy,
            2 * (x * z + w * y) * sz,
            2 * (x * y + w * z) * sx,
            (1 - 2 * (x * x + z * z)) * sy,
            2 * (y * z - w * x) * sz,
            2 * (x * z - w * y) * sx,
            2 * (y * z + w * x) * sy,
            (1 - 2 * (x * x + y * y)) * sz,
        ],
        -1,
    ).reshape(-1, 3, 3)
    return m @ m.transpose(1, 2)


def sh_to_rgb(sh: Tensor, means: Tensor, eye: Tensor | np.ndarray | None, degree: int) -> Tensor:
    """SH coefficients -> RGB in [0, 1] for the direction from ``eye`` to each Gaussian (gsplat's convention).

    Args:
        sh: Tensor  # [N, K, 3] coefficients, [:, 0] = DC
        means: Tensor  # [N, 3] world centres
        eye: viewer camera centre [3] (None or ``degree == 0``: band 0 only, view independent)
        degree: SH degree to evaluate (<= sqrt(K) - 1)

    Returns:
        Tensor  # [N, 3]
    """
    if degree == 0 or eye is None:
        return (sh[:, 0] * SH_C0 + 0.5).clamp_(0.0, 1.0)
    e = torch.as_tensor(np.asarray(eye, np.float32), dtype=means.dtype, device=means.device)
    return eval_sh_colors(degree, means - e, sh).clamp_(0.0, 1.0)


@numba.njit(cache=CACHE, nogil=True, fastmath=True)
def _viewer_kernel(means, quats, scales, sh, eye, degree, cov, rgb):  # pragma: no cover - numba
    """Fused :func:`covariances_from` + :func:`sh_to_rgb` (degree 0..3; ``degree < 0``: band 0 only)."""
    n = means.shape[0]
    b = np.empty(16, np.float32)
    b[0] = 0.28209479177387814
    for i in range(n):
        w, x, y, z = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        sx, sy, sz = scales[i, 0], scales[i, 1], scales[i, 2]
        m00 = (1 - 2 * (y * y + z * z)) * sx
        m01 = 2 * (x * y - w * z) * sy
        m02 = 2 * (x * z + w * y) * sz
        m10 = 2 * (x * y + w * z) * sx
        m11 = (1 - 2 * (x * x + z * z)) * sy
        m12 = 2 * (y * z - w * x) * sz
        m20 = 2 * (x * z - w * y) * sx
        m21 = 2 * (y * z + w * x) * sy
        m22 = (1 - 2 * (x * x + y * y)) * sz
        c00 = m00 * m00 + m01 * m01 + m02 * m02
        c01 = m00 * m10 + m01 * m11 + m02 * m12
        c02 = m00 * m20 + m01 * m21 + m02 * m22
        c11 = m10 * m10 + m11 * m11 + m12 * m12
        c12 = m10 * m20 + m11 * m21 + m12 * m22
        c22 = m20 * m20 + m21 * m21 + m22 * m22
        cov[i, 0, 0] = c00
        cov[i, 0, 1] = c01
        cov[i, 0, 2] = c02
        cov[i, 1, 0] = c01
        cov[i, 1, 1] = c11
        cov[i, 1, 2] = c12
        cov[i, 2, 0] = c02
        cov[i, 2, 1] = c12
        cov[i, 2, 2] = c22
        nb = 1
        if degree > 0:
            dx, dy, dz = means[i, 0] - eye[0], means[i, 1] - eye[1], means[i, 2] - eye[2]
            r = 1.0 / np.sqrt(max(dx * dx + dy * dy + dz * dz, 1e-12))
            dx, dy, dz = dx * r, dy * r, dz * r
            b[1] = -0.48860251190292 * dy
            b[2] = 0.48860251190292 * dz
            b[3] = -0.48860251190292 * dx
            nb = 4
            if degree > 1:
                z2 = dz * dz
                c1 = dx * dx - dy * dy
                s1 = 2.0 * dx * dy
                tb = -1.092548430592079 * dz
                b[4] = 0.5462742152960395 * s1
                b[5] = tb * dy
                b[6] = 0.9461746957575601 * z2 - 0.3153915652525201
                b[7] = tb * dx
                b[8] = 0.5462742152960395 * c1
                nb = 9
                if degree > 2:
                    c2 = dx * c1 - dy * s1
                    s2 = dx * s1 + dy * c1
                    tc = -2.285228997322329 * z2 + 0.4570457994644658
                    tb3 = 1.445305721320277 * dz
                    b[9] = -0.5900435899266435 * s2
                    b[10] = tb3 * s1
                    b[11] = tc * dy
                    b[12] = dz * (1.865881662950577 * z2 - 1.119528997770346)
                    b[13] = tc * dx
                    b[14] = tb3 * c1
                    b[15] = -0.5900435899266435 * c2
                    nb = 16
        for c in range(3):
            v = 0.5
            for k in range(nb):
                v += b[k] * sh[i, k, c]
            rgb[i, c] = min(max(v, 0.0), 1.0)


def viewer_arrays(
    means: Tensor, quats: Tensor, scales: Tensor, sh: Tensor, eye: np.ndarray | None, degree: int
) -> tuple[np.ndarray, np.ndarray]:
    """Fused numba path of :func:`covariances_from` and :func:`sh_to_rgb` (same results, float32 numpy).

    Args:
        means: Tensor  # [N, 3]
        quats: Tensor  # [N, 4] unit wxyz
        scales: Tensor  # [N, 3]
        sh: Tensor  # [N, K, 3], K >= (degree + 1)^2
        eye: viewer camera centre [3] (None: band 0 only)
        degree: 0..3

    Returns:
        (covariances [N, 3, 3], rgbs [N, 3])
    """
    f = lambda t: np.ascontiguousarray(t.detach().float().cpu().numpy())  # noqa: E731
    n = means.shape[0]
    if not 0 <= degree <= 3 or sh.shape[1] < (degree + 1) ** 2:
        raise ValueError(f"degree must be in [0, 3] with sh [N, >= (degree+1)^2, 3], got {degree}, {list(sh.shape)}")
    cov, rgb = np.empty((n, 3, 3), np.float32), np.empty((n, 3), np.float32)
    e = np.zeros(3, np.float32) if eye is None else np.asarray(eye, np.float32).reshape(3)
    _viewer_kernel(f(means), f(quats), f(scales), f(sh), e, -1 if eye is None else int(degree), cov, rgb)
    return cov, rgb


class LiveGaussians:
    """Frame-by-frame viewer Gaussians of a :class:`~gsavatar.drive.driver.Driver` (module docstring).

    Args:
        driver: the driver whose net, latent source and mode are used (its cameras are not).
        sh0_only: colour from SH band 0 only (view independent; also when no ``eye`` is given).
        mean_latent: the training frames' mean latent [A, L] for mode :data:`MEAN_LATENT` (computed on
            first use when None).
    """

    def __init__(self, driver: Driver, sh0_only: bool = False, mean_latent: Tensor | None = None) -> None:
        self.driver = driver
        self.sh0_only = sh0_only
        self._mean = mean_latent
        self.mode: str = driver.config.mode
        """The latent source: a drive mode or :data:`MEAN_LATENT`."""
        self.pose_offset = torch.zeros(driver.pose_dim)
        """Added to every frame's pose (the viewer's pose panel), radians.  # [P]"""
        self.timings: dict[str, float] = defaultdict(float)
        """Seconds spent per part since the last :meth:`reset_timings`."""
        self.frames = 0
        self.t = -1

    # ------------------------------------------------------------------ modes
    @staticmethod
    def modes(driver: Driver) -> list[str]:
        """Latent sources this driver's run supports: registered drive modes whose needs it meets, then
        :data:`MEAN_LATENT` (models without appearance latents: their one pose-only source)."""
        if not driver.has_latents:
            return [driver.config.mode]
        out = []
        for name, cls in LATENT_SOURCES.items():
            if not cls.in_viewer:
                continue
            if cls.needs_predictor and driver.predictor is None:
                continue
            if cls.needs_texture and driver.net.encoder is None:
                continue
            out.append(name)
        if driver.net.encoder is not None:
            out.append(MEAN_LATENT)
        return out

    def set_mode(self, mode: str) -> None:
        """Switch the latent source (takes effect from the next :meth:`start`); raises ValueError for a mode
        the run cannot drive (no predictor, no encoder)."""
        if mode == self.mode:
            return
        if mode == MEAN_LATENT:
            if self.driver.net.encoder is None:
                raise ValueError(f"mode {MEAN_LATENT!r} needs the run's appearance encoder")
            self.mode = mode
            return
        if mode not in LATENT_SOURCES:
            raise ValueError(f"mode must be one of {'/'.join([*LATENT_SOURCES, MEAN_LATENT])}, got {mode!r}")
        if mode != self.driver.config.mode:
            self.driver = self.driver.with_mode(mode)  # raises for a missing predictor / encoder
        self.mode = mode
        self.t = -1

    def mean_latent(self) -> Tensor:
        """The training frames' mean encoder latent (computed once).  # [A, L]"""
        if self._mean is None:
            d = self.driver
            self._mean = mean_train_latent(d.net, d.scene, d.device, d.train_cfg.texture_source)
        return self._mean

    def texture_needed_at(self, t: int) -> bool:
        """Whether frame ``t`` since :meth:`start` needs ``FrameInputs.texture``."""
        return self.mode != MEAN_LATENT and self.driver.has_latents and self.driver.texture_needed_at(t)

    @property
    def needs_textures(self) -> bool:
        return self.mode != MEAN_LATENT and self.driver.has_latents and self.driver.needs_textures

    # ------------------------------------------------------------------ frames
    def reset_timings(self) -> None:
        self.timings = defaultdict(float)
        self.frames = 0

    def _offset(self, x: FrameInputs) -> FrameInputs:
        if not bool(self.pose_offset.any()):
            return x
        return x._replace(pose=torch.as_tensor(x.pose, dtype=torch.float32) + self.pose_offset)

    @torch.inference_mode()
    def start(self, first: FrameInputs) -> None:
        """Start a sequence at ``first`` (the next :meth:`next` is this frame)."""
        tic = time.perf_counter()
        if self.mode != MEAN_LATENT:
            self.driver.start(self._offset(first))
        else:
            self.mean_latent()
        self.t = 0
        self.timings["predictor"] += time.perf_counter() - tic

    @torch.inference_mode()
    def latents(self, x: FrameInputs) -> Tensor:
        """Advance the latent source by one frame (no avatar pass): latents of the next frame.  # [A, L]"""
        if self.t < 0:
            raise ValueError("call start(first_frame_inputs) before next()")
        tic = time.perf_counter()
        if self.mode == MEAN_LATENT:
            lat = self.mean_latent()
        else:
            lat = self.driver.step(self._offset(x), render=False).latents
        self.t += 1
        self.timings["predictor"] += time.perf_counter() - tic
        return lat

    @torch.inference_mode()
    def gaussians(self, x: FrameInputs, latents: Tensor, eye: Tensor | np.ndarray | None = None) -> ViewerGaussians:
        """Viewer Gaussians of inputs ``x`` with latents [A, L] (``eye``: the viewer's camera centre [3])."""
        d = self.driver
        tic = time.perf_counter()
        xc = d.check_inputs(self._offset(x))
        deg = 0 if self.sh0_only else d.sh_degree  # band 0 only: the avatar skips the higher bands' correctives
        av = d.net(xc.batch(latents.to(d.device) if d.has_latents else None), sh_degree=deg).avatar
        t1 = time.perf_counter()
        e = None if self.sh0_only or eye is None else np.asarray(eye, np.float32)
        cov, rgb = viewer_arrays(av.means[0], av.quats[0], av.scales[0], av.sh[0], e, deg)
        t2 = time.perf_counter()
        out = ViewerGaussians(
            np.ascontiguousarray(av.means[0].float().cpu().numpy()),
            cov,
            rgb,
            np.ascontiguousarray(av.opacities[0, :, None].float().cpu().numpy()),
        )
        for k, v in (("avatar", t1 - tic), ("covariance + SH -> RGB", t2 - t1)):
            self.timings[k] += v
        self.frames += 1
        return out

    def next(self, x: FrameInputs, eye: Tensor | np.ndarray | None = None) -> ViewerGaussians:
        """Latents and viewer Gaussians of the next frame (``eye``: the viewer's camera centre [3])."""
        return self.gaussians(x, self.latents(x), eye)


def export_drive_plys(args) -> int:
    """``avatar-drive --export-ply DIR``: every driven frame's posed Gaussians as ``DIR/{t:06d}.ply``.

    ``args``: :class:`gsavatar.drive.cli.DriveArgs` (run, motion and its loading options, the drive
    configuration, ``export_ply``, ``up_axis``, ``force``). Returns the number of files written.
    """
    from pathlib import Path

    cfg = args.config()
    d = Driver(args.run, cfg)
    motion = load_driving_motion(
        args.motion,
        d.scene.capture.rig,
        d.fps,
        fps=args.motion_fps or None,
        start=args.start,
        count=args.count or None,
        split=args.split,
    )
    if motion.face is not None and motion.face.shape[1] != d.face_dim:
        raise SchemaError(args.motion, "face", f"has {motion.face.shape[1]} columns, the avatar expects {d.face_dim}")
    textures = texture_source(motion, d.scene, cfg.textures) if d.needs_textures else None
    out = claim_output_dir(Path(args.export_ply), "drive", args.force, register=True)
    T = motion.num_frames
    with torch.inference_mode(), progress_bar(f"avatar-drive --export-ply ({T} frames)", T) as bar:

        def inputs(t: int) -> FrameInputs:
            return motion_inputs(motion, t, textures(t) if d.texture_needed_at(t) else None)

        first = inputs(0)
        d.start(first)
        for t in range(T):
            x = first if t == 0 else inputs(t)
            lat = d.step(x, render=False).latents
            xc = d.check_inputs(x)
            av = d.net(xc.batch(lat.to(d.device) if d.has_latents else None), sh_degree=d.sh_degree).avatar
            export_frame_ply(out / f"{t:06d}.ply", av, 0, up_axis=args.up_axis)
            bar.advance()
    print(f"avatar-drive: {T} PLY files (up axis {args.up_axis}) -> {out}")
    return T
