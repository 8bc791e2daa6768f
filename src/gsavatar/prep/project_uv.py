"""Per-frame UV texture by multi-view projection onto the posed template (paper, supp. C).

For one frame:

1. every texel of the :class:`~gsavatar.prep.uv_atlas.TexelMap` becomes a surface point
   (barycentric interpolation over its posed triangle) with a smooth normal
   (interpolated area-weighted vertex normals);
2. per view, a texel is *seen* when it is in front of the camera, faces it
   (``cos(normal, to_camera) >= min_cos``: back-facing and grazing texels are dropped),
   projects inside the image (OpenCV distortion, same model as
   :func:`gsavatar.geometry.camera.project`), all four bilinear taps lie in the
   **eroded** foreground mask, and it is visible; its colour is the bilinear image sample;
3. samples are fused per texel: ``median_band`` (the paper) takes the median luminance
   over the views, drops samples whose luminance is outside ``[lo, hi] x median`` and
   averages the RGB of the rest; ``mean`` averages all samples (for comparison).

Two implementations, selected by ``ProjectConfig.visibility``:

- ``zbuffer`` (default): compiled numba kernels (:mod:`gsavatar.prep.zbuffer`). Per view a
  triangle-id buffer of the posed mesh is rasterized on the camera's pinhole grid (cropped to
  the mesh's bounding box; back faces culled when the mesh is closed); a texel is visible
  unless the front triangle at its nearest grid pixel -- other than its own triangle and their
  1-ring -- lies more than ``occlusion_eps`` in front of it along its exact ray (plane
  depth). Sampling and fusion run texel-block by texel-block (Morton order of the texels, so a
  block is a compact image patch in every view) with the samples in cache. Cost scales with
  image pixels (rasterization) and texels x views, not with ray casting.
- ``rays``: the numpy + open3d reference: one occlusion ray (``RaycastingScene.test_occlusions``)
  per texel and view that passed the cheap tests, from ``occlusion_eps`` off the texel to the
  camera centre. Exact at occluding contours; ~5x slower at 1024^2 (docs/prep.md).

They agree except within about a pixel of occluding contours (tests/prep/test_project_uv_zbuffer.py).
The z-buffer path keeps all views' images of a frame in memory (the fused kernel samples every
view per texel block); the ray path holds ``N_texels x N_views x 13`` bytes of samples plus one
view's images at a time when ``views`` is a generator (:func:`iter_frame_views`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from gsavatar.data_schema.capture import Camera, Capture
from gsavatar.data_schema.prepared import resize_face_mask
from gsavatar.data_schema.template import Template
from gsavatar.geometry.camera import distort, undistort
from gsavatar.prep.uv_atlas import TexelMap, build_texel_map, ensure_uvs
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_image, read_mask

LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 luminance weights used as the texel 'intensity' of the median-band rule."""


@dataclass(frozen=True)
class ProjectConfig:
    """Settings of the per-frame UV texel projection."""

    tex_size: int | None = None
    """UV texture resolution (square); None = derived from the capture by ``avatar-prep`` (see
    ``stages.auto_tex_size``: 512 for 256^2 views, capped at the paper's 1024)."""
    erode_px: int = 5
    """Side of the square kernel eroding the foreground mask (``mask > mask_threshold``) before sampling; 0 = no
    erosion."""
    min_cos: float = 0.1
    """Minimum cosine between the texel normal and the direction to the camera; below it the texel is
    back-facing/grazing and not seen."""
    band: tuple[float, float] = (0.8, 1.1)
    """Kept luminance range ``[lo, hi]`` as multiples of the per-texel median luminance (``median_band`` fusion)."""
    fusion: Literal["median_band", "mean"] = "median_band"
    """``median_band``: the paper's rule; ``mean``: plain average of all samples (for comparison)."""
    mask_face: bool = True
    """Blank the face region (``template.face_uv_mask``): texture 0, ``valid`` False there (the face is explained
    by the face embedding)."""
    mask_threshold: float = 0.5
    """Foreground threshold on the [0, 1] mask."""
    occlusion_eps: float = 1e-3
    """Occluders closer than this (metres, along the ray texel -> camera) do not hide a texel: the ``rays`` path starts
    its ray this far off the texel, the ``zbuffer`` path tolerates this depth difference."""
    gutter_px: float = 1.0
    """Texels outside every UV triangle but within this distance (texels) of one are projected too (seam
    dilation); used when building the TexelMap."""
    chunk: int = 1 << 18
    """Texels processed per vectorised batch (bounds temporary memory; ``rays`` path only)."""
    visibility: Literal["zbuffer", "rays"] = "zbuffer"
    """``zbuffer``: compiled per-texel kernels with one triangle-id/depth buffer per view (fast, the default);
    ``rays``: the numpy + open3d occlusion-ray reference path. They agree except within ~1 pixel of
    occluding contours (tests/prep/test_project_uv_zbuffer.py)."""

    def __post_init__(self) -> None:
        if self.tex_size is not None and (not isinstance(self.tex_size, int) or self.tex_size < 1):
            raise ValueError(f"tex_size must be a positive integer (or None = derived), got {self.tex_size!r}")
        if self.erode_px < 0:
            raise ValueError(f"erode_px must be >= 0, got {self.erode_px}")
        lo, hi = self.band
        if not (0 <= lo <= 1 <= hi):
            raise ValueError(f"band must satisfy 0 <= lo <= 1 <= hi, got {self.band}")
        if self.fusion not in ("median_band", "mean"):
            raise ValueError(f"fusion must be 'median_band' or 'mean', got {self.fusion!r}")
        if not -1 <= self.min_cos <= 1:
            raise ValueError(f"min_cos must be in [-1, 1], got {self.min_cos}")
        if self.chunk < 1:
            raise ValueError(f"chunk must be >= 1, got {self.chunk}")
        if self.visibility not in ("zbuffer", "rays"):
            raise ValueError(f"visibility must be 'zbuffer' or 'rays', got {self.visibility!r}")


class TexelFusion(NamedTuple):
    texture: np.ndarray
    """Fused RGB per texel, 0 where not valid.  # [H, W, 3] float32"""
    count: np.ndarray
    """Views whose sample was kept by the fusion rule.  # [H, W] uint8"""
    seen: np.ndarray
    """Views that saw the texel (visible, in the eroded mask), before the band filter.  # [H, W] uint8"""
    valid: np.ndarray
    """count > 0 (and outside the masked face region).  # [H, W] bool"""


ImageView = tuple[Camera, np.ndarray, "np.ndarray | None"]
"""(camera, image [H,W,3] float [0,1], foreground mask [H,W] float [0,1] or None = all foreground)."""


# --------------------------------------------------------------------------- geometry helpers
def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; zero for isolated/degenerate vertices). -> [V, 3] float64."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |fn| = 2 area
    n = np.zeros_like(v)
    idx = f.ravel()
    for c in range(3):
        n[:, c] = np.bincount(idx, weights=np.repeat(fn[:, c], 3), minlength=len(v))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)


def erode_mask(mask: np.ndarray | None, shape: tuple[int, int], erode_px: int, threshold: float = 0.5) -> np.ndarray:
    """Binary foreground (``mask > threshold``) eroded by a ``erode_px`` square kernel. -> [H, W] bool."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    fg = np.asarray(mask) > threshold
    if erode_px > 1:
        import cv2

        # bool is stored as 0/1 bytes: erode the uint8 view, read the 0/1 result back as bool (no copies)
        fg = cv2.erode(
            fg.view(np.uint8), np.ones((erode_px, erode_px), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1
        ).view(bool)
    return fg


def _fov_r2_limit(cam: Camera) -> float:
    """Largest squared normalised radius a point may have before distortion is applied.

    Points far outside the field of view can be folded back into the image by the
    polynomial distortion model; they are rejected by this bound (1.2x the radius of
    the undistorted image border, and never past where the radial map stops being
    monotonic).
    """
    d = np.asarray(cam.dist, dtype=np.float64)
    if not np.any(d):
        return np.inf
    W, H = cam.width, cam.height
    t = np.linspace(0, 1, 65)
    border = np.concatenate(
        [
            np.stack([t * (W - 1), np.zeros_like(t)], 1),
            np.stack([t * (W - 1), np.full_like(t, H - 1)], 1),
            np.stack([np.zeros_like(t), t * (H - 1)], 1),
            np.stack([np.full_like(t, W - 1), t * (H - 1)], 1),
        ]
    )
    xd = (border - cam.K[:2, 2]) @ np.linalg.inv(cam.K[:2, :2]).T
    xn = undistort(xd, d, iters=50)
    converged = np.abs(distort(xn, d) - xd).max(axis=1) < 1e-4
    r_border = np.sqrt((xn[converged] ** 2).sum(1)).max() * 1.2 if converged.any() else np.inf
    # monotonic range of r -> r * (1 + k1 r^2 + k2 r^4 + k3 r^6)
    k1, k2, _, _, k3 = d
    r = np.linspace(0, min(r_border, 20.0) if np.isfinite(r_border) else 20.0, 4001)
    deriv = 1 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6
    bad = np.flatnonzero(deriv <= 0)
    r_mono = r[bad[0]] if bad.size else np.inf
    r_lim = min(r_border, r_mono)
    return float(r_lim**2)


# --------------------------------------------------------------------------- sampling
class _ViewCtx(NamedTuple):
    cam: Camera
    image: (
        np.ndarray
    )  # [H*W, 3] float32 (z-buffer path: [h*w, 4] uint8/float32 of `region`, alpha = the quad foreground)
    fg: np.ndarray | None  # [H*W] bool eroded foreground (None on the z-buffer path: in the image's alpha)
    center: np.ndarray  # [3]
    r2max: float
    region: tuple[int, int, int, int] | None = None  # z-buffer path: (x0, y0, w, h) of the image in `image`


def _camera_key(cam: Camera) -> tuple:
    """What the per-camera caches (distortion radius bound, pinhole grid) depend on."""
    return (
        cam.name,
        tuple(np.asarray(cam.dist, dtype=np.float64).tolist()),
        cam.width,
        cam.height,
        tuple(cam.K.ravel().tolist()),
    )


def _sample_view(
    P: np.ndarray, Nrm: np.ndarray, v: _ViewCtx, scene, cfg: ProjectConfig, rgb: np.ndarray, ok: np.ndarray
) -> None:
    """Sample one view for a chunk of texel points P [3, n] (world) with unit normals Nrm [3, n];
    writes rgb [n, 3] float32 and ok [n] bool in place (zero/False on entry).

    Structure-of-arrays (x, y, z rows) keeps every per-texel operation on contiguous
    1-D arrays; expensive steps only run on the texels that survived the cheap ones.
    No BLAS calls on purpose (``[N,3] @ [3,3]``): a multithreaded OpenBLAS spinning next
    to open3d's ray-casting threads made the whole loop ~3x slower on 2 cores.
    """
    cam = v.cam
    R, T, c = cam.R, cam.T, v.center
    z = R[2, 0] * P[0] + R[2, 1] * P[1] + R[2, 2] * P[2] + T[2]
    tx, ty, tz = c[0] - P[0], c[1] - P[1], c[2] - P[2]
    dist = np.sqrt(tx * tx + ty * ty + tz * tz)
    # in front of the camera and cos(normal, to_camera) >= min_cos (no per-texel division)
    cand = np.flatnonzero((z > 1e-6) & (Nrm[0] * tx + Nrm[1] * ty + Nrm[2] * tz >= cfg.min_cos * dist))
    if cand.size == 0:
        return
    Pc = P[:, cand]
    zc = z[cand]
    xn = (R[0, 0] * Pc[0] + R[0, 1] * Pc[1] + R[0, 2] * Pc[2] + T[0]) / zc
    yn = (R[1, 0] * Pc[0] + R[1, 1] * Pc[1] + R[1, 2] * Pc[2] + T[1]) / zc
    if np.isfinite(v.r2max):
        keep = np.flatnonzero(xn * xn + yn * yn <= v.r2max)
        cand, xn, yn = cand[keep], xn[keep], yn[keep]
    if np.any(cam.dist):
        d = distort(np.stack([xn, yn], axis=1), cam.dist)
        xn, yn = d[:, 0], d[:, 1]
    K = cam.K
    px = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    py = K[1, 1] * yn + K[1, 2]
    W, H = cam.width, cam.height
    inb = np.flatnonzero((px >= 0) & (px <= W - 1) & (py >= 0) & (py <= H - 1))
    if inb.size == 0:
        return
    cand, px, py = cand[inb], px[inb], py[inb]
    x0 = np.minimum(px.astype(np.int64), max(W - 2, 0))  # px >= 0: truncation == floor
    y0 = np.minimum(py.astype(np.int64), max(H - 2, 0))
    dx = 1 if W > 1 else 0
    dy = W if H > 1 else 0
    i00 = y0 * W + x0
    fg = v.fg
    sel = np.flatnonzero(fg[i00] & fg[i00 + dx] & fg[i00 + dy] & fg[i00 + dy + dx])  # all 4 bilinear taps
    if sel.size == 0:
        return
    cand, i00 = cand[sel], i00[sel]
    fx = (px[sel] - x0[sel]).astype(np.float32)[:, None]
    fy = (py[sel] - y0[sel]).astype(np.float32)[:, None]
    # occlusion: segment from just off the texel (towards the camera) to the camera centre
    if scene is not None:
        import open3d as o3d

        s = cfg.occlusion_eps / np.maximum(dist[cand], 1e-12)
        rays = np.empty((cand.size, 6), dtype=np.float32)
        for k, t in enumerate((tx, ty, tz)):
            o = P[k, cand] + t[cand] * s
            rays[:, k] = o
            rays[:, 3 + k] = c[k] - o
        vis = np.flatnonzero(~scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy().astype(bool))
        if vis.size == 0:
            return
        cand, i00, fx, fy = cand[vis], i00[vis], fx[vis], fy[vis]
    img = v.image
    col = (img[i00] * (1 - fx) + img[i00 + dx] * fx) * (1 - fy) + (
        img[i00 + dy] * (1 - fx) + img[i00 + dy + dx] * fx
    ) * fy
    finite = np.isfinite(col[:, 0] + col[:, 1] + col[:, 2])
    if not finite.all():
        cand, col = cand[finite], col[finite]
    rgb[cand] = col
    ok[cand] = True


# --------------------------------------------------------------------------- fusion
def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance in float64. [..., 3] -> [...]."""
    rgb = np.asarray(rgb)
    r, g, b = (rgb[..., i].astype(np.float64) for i in range(3))
    return LUMA[0] * r + LUMA[1] * g + LUMA[2] * b


def _fuse_views(rgbs: Sequence[np.ndarray], oks: Sequence[np.ndarray], fusion: str, band: tuple[float, float]):
    """:func:`fuse_samples` on per-view arrays (rgb [n,3], ok [n] per view), without stacking the colours."""
    C = len(rgbs)
    n = oks[0].shape[0] if C else 0
    if C == 0:
        return np.zeros((n, 3), np.float32), np.zeros(n, np.int64), np.zeros(n, np.int64)
    ok = np.stack(oks, axis=1)  # [n, C]
    seen = ok.sum(1)
    if fusion == "mean":
        keep = ok
    elif fusion == "median_band":
        L = np.empty((n, C), dtype=np.float64)
        for c in range(C):
            L[:, c] = np.where(oks[c], luminance(rgbs[c]), np.inf)
        Ls = np.sort(L, axis=1)
        lo_i = np.clip((seen - 1) // 2, 0, C - 1)[:, None]
        hi_i = np.clip(seen // 2, 0, C - 1)[:, None]
        med = (np.take_along_axis(Ls, lo_i, axis=1) + np.take_along_axis(Ls, hi_i, axis=1)) / 2
        keep = ok & (L >= band[0] * med) & (L <= band[1] * med)
        empty = np.flatnonzero((seen > 0) & ~keep.any(1))
        if empty.size:  # band kept nothing (even count, two middle values far apart): use those two
            order = np.argsort(L[empty], axis=1, kind="stable")
            keep[empty, order[np.arange(empty.size), lo_i[empty, 0]]] = True
            keep[empty, order[np.arange(empty.size), hi_i[empty, 0]]] = True
    else:
        raise ValueError(f"unknown fusion {fusion!r}")
    count = keep.sum(1)
    total = np.zeros((n, 3), dtype=np.float64)
    for c in range(C):  # accumulate in view order (float64)
        total += np.where(keep[:, c, None], rgbs[c], 0).astype(np.float64)
    colour = np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], 0.0)
    return colour.astype(np.float32), count, seen


def fuse_samples(
    rgb: np.ndarray, ok: np.ndarray, fusion: str = "median_band", band: tuple[float, float] = (0.8, 1.1)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse per-texel view samples.

    rgb [N, C, 3], ok [N, C] bool -> (colour [N, 3] float32 (0 where nothing kept),
    count [N] int64 samples kept, seen [N] int64 samples available). Values of ``rgb``
    where ``ok`` is False are ignored.

    ``median_band``: median luminance m (:func:`luminance`) over the available samples
    (mean of the two middle values for an even count), keep samples with
    ``lo*m <= L <= hi*m``, average their RGB. If the band keeps nothing (only possible
    for an even count whose two middle values are far apart), the two middle samples
    are averaged instead. ``mean``: average of all available samples.
    """
    rgb = np.asarray(rgb)
    ok = np.asarray(ok, dtype=bool)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or ok.shape != rgb.shape[:2]:
        raise ValueError(f"expected rgb [N, C, 3] and ok [N, C], got {rgb.shape} and {ok.shape}")
    if fusion not in ("median_band", "mean"):
        raise ValueError(f"unknown fusion {fusion!r}")
    if rgb.shape[1] == 0:
        N = rgb.shape[0]
        return np.zeros((N, 3), np.float32), np.zeros(N, np.int64), np.zeros(N, np.int64)
    return _fuse_views([rgb[:, c] for c in range(rgb.shape[1])], [ok[:, c] for c in range(ok.shape[1])], fusion, band)


# --------------------------------------------------------------------------- projector
@dataclass
class _ZFrame:
    """One frame's inputs of the z-buffer kernels (lists hold one entry per view with foreground)."""

    P: np.ndarray  # [3, N] float64 texel points
    Nrm: np.ndarray  # [3, N] float64 unit texel normals
    num_views: int  # views consumed (including ones without foreground)
    index: list[int]  # position of each kept view among all views
    cams: list[np.ndarray]  # [CAM_SIZE] float64 packed cameras (zbuffer.CAMERA_ROW)
    imgs: list[
        np.ndarray
    ]  # [h*w, 4] float32 or uint8 of the view's region, alpha = quad foreground (zbuffer.region_rgba)
    tri_ids: list[np.ndarray]  # [Hg, Wg] int32 front triangle (-1 empty)
    planes: list[np.ndarray]  # [F, 4] float64 camera-space triangle planes


class UVProjector:
    """Projects frames onto one texel map; per-texel lookups are precomputed once.

    faces [F,3] (template triangles, vertex indices), ``texel_map`` from
    :func:`~gsavatar.prep.uv_atlas.build_texel_map`, optional ``face_uv_mask`` (any
    resolution, True = face) applied when ``config.mask_face``.
    """

    def __init__(
        self,
        faces: np.ndarray,
        texel_map: TexelMap,
        config: ProjectConfig | None = None,
        face_uv_mask: np.ndarray | None = None,
    ) -> None:
        if config is None:
            config = ProjectConfig(tex_size=int(texel_map.size))
        elif config.tex_size != texel_map.size:
            raise ValueError(
                f"texel map is {texel_map.size}^2 but config.tex_size is {config.tex_size}; "
                "build it with prepare_texel_map(template, config)"
            )
        self.config = config
        self.faces = np.asarray(faces, dtype=np.int64)
        self.size = int(texel_map.size)
        valid = texel_map.face >= 0
        if self.config.mask_face and face_uv_mask is not None:
            self.face_region = resize_face_mask(face_uv_mask, self.size)
            valid &= ~self.face_region
        else:
            self.face_region = None
        self.texels = np.flatnonzero(valid.ravel())  # [N] flat texel index
        tri = texel_map.face.ravel()[self.texels].astype(np.int64)
        if tri.size and tri.max() >= len(self.faces):
            raise ValueError(f"texel map references triangle {tri.max()} but the mesh has {len(self.faces)}")
        self.corner_vids = self.faces[tri]  # [N, 3]
        self.bary = texel_map.bary.reshape(-1, 3)[self.texels].astype(np.float64)  # [N, 3]
        self._bary_soa = tuple(np.ascontiguousarray(self.bary[:, k]) for k in range(3))
        self._corner_soa = tuple(np.ascontiguousarray(self.corner_vids[:, k]) for k in range(3))
        # z-buffer path: texels in Morton (Z-curve) order of their texel coordinates, so that a block of the
        # fused kernel is a compact UV tile -> a compact surface patch -> a compact image patch in every view
        ys, xs = np.divmod(self.texels, self.size)
        self._zorder = np.argsort(_morton(ys, xs), kind="stable")  # [N] position in self.texels
        self._z_texels = self.texels[self._zorder]
        self._z_corners = np.ascontiguousarray(self.corner_vids[self._zorder])
        self._z_bary = np.ascontiguousarray(self.bary[self._zorder])
        self._z_tri = np.ascontiguousarray(tri[self._zorder], dtype=np.int32)  # [N] texel triangle (self test)
        self._r2 = {}
        self._grids = {}
        self._rgba: dict[int, np.ndarray] = {}  # per view slot: the kernels' RGBA image buffer, refilled each frame
        self._closed = is_closed(self.faces)  # back faces can be culled from the z-buffer

    @property
    def num_texels(self) -> int:
        return int(self.texels.size)

    def surface(self, vertices: np.ndarray, frame: int | str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Posed surface point and unit normal of every projected texel. -> [N,3], [N,3] float64."""
        P, Nrm = self._surface_soa(vertices, frame)
        return P.T, Nrm.T

    def _check_vertices(self, vertices: np.ndarray, frame) -> np.ndarray:
        """Posed vertices as float64 [V, 3]; ValueError naming ``frame`` if mis-shaped, NaN/Inf or too few."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"frame {frame}: posed vertices must be [V, 3], got {v.shape}")
        bad = ~np.all(np.isfinite(v), axis=1)
        if bad.any():
            raise ValueError(
                f"frame {frame}: {int(bad.sum())} posed vertices are NaN/Inf (first: vertex {int(np.argmax(bad))})"
            )
        if len(self.faces) and self.faces.max() >= len(v):
            raise ValueError(
                f"frame {frame}: faces reference vertex {self.faces.max()} but only {len(v)} posed vertices given"
            )
        return np.ascontiguousarray(v)

    def _surface_soa(self, vertices: np.ndarray, frame) -> tuple[np.ndarray, np.ndarray]:
        """Texel points and unit normals as contiguous rows. -> [3, N], [3, N] float64."""
        v = self._check_vertices(vertices, frame)
        n = vertex_normals(v, self.faces)
        vT, nT = np.ascontiguousarray(v.T), np.ascontiguousarray(n.T)
        b0, b1, b2 = self._bary_soa
        c0, c1, c2 = self._corner_soa
        P = np.empty((3, self.num_texels))
        Nrm = np.empty((3, self.num_texels))
        for k in range(3):
            P[k] = b0 * vT[k, c0] + b1 * vT[k, c1] + b2 * vT[k, c2]
            Nrm[k] = b0 * nT[k, c0] + b1 * nT[k, c1] + b2 * nT[k, c2]
        length = np.sqrt(Nrm[0] * Nrm[0] + Nrm[1] * Nrm[1] + Nrm[2] * Nrm[2])
        good = length > 1e-12
        Nrm *= np.where(good, 1.0 / np.where(good, length, 1.0), 0.0)
        return P, Nrm

    def _view_ctx(
        self, view: ImageView, frame, keep_uint8: bool = False, quad: bool = False, slot: int = -1
    ) -> _ViewCtx | None:
        """Checked view: image [H*W, 3] (float32 in [0, 1]; uint8 kept as is when ``keep_uint8``), eroded
        foreground [H*W] bool, camera centre and distortion radius bound. None when the mask has no foreground.
        ``quad`` (the z-buffer path): instead, the RGBA buffer of the mask's region with the
        :func:`~gsavatar.prep.zbuffer.quad_foreground` flag as alpha (:func:`~gsavatar.prep.zbuffer.region_rgba`)
        and that region; ``slot``: the view's position in the frame, whose buffer from the previous frame is
        refilled."""
        cam, image, mask = view
        image = np.asarray(image)
        if image.dtype == np.uint8 and not keep_uint8:
            image = image.astype(np.float32) / 255.0
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        if image.shape[:2] != (cam.height, cam.width) or image.shape[2] < 3:
            raise ValueError(
                f"frame {frame}: image of camera {cam.name!r} is {image.shape}, "
                f"calibration says {cam.height}x{cam.width}x3"
            )
        if mask is not None and np.asarray(mask).shape[:2] != (cam.height, cam.width):
            raise ValueError(
                f"frame {frame}: mask of camera {cam.name!r} is {np.asarray(mask).shape}, "
                f"calibration says {cam.height}x{cam.width}"
            )
        m = mask if mask is None or np.asarray(mask).ndim == 2 else np.asarray(mask)[..., 0]
        key = _camera_key(cam)
        if key not in self._r2:
            self._r2[key] = _fov_r2_limit(cam)
        if quad:  # the z-buffer kernels read the foreground from the alpha channel of the mask's region of the image
            # local: zbuffer imports numba (compiled kernels); every avatar-prep command imports this module
            from gsavatar.prep.zbuffer import region_rgba

            got = region_rgba(
                np.asarray(image[..., :3], dtype=np.uint8 if image.dtype == np.uint8 else np.float32),
                m,
                self.config.erode_px,
                self.config.mask_threshold,
                self._rgba.get(slot) if slot >= 0 else None,
            )
            if got is None:
                return None
            img, region = got
            buf = self._rgba.get(slot)
            if slot >= 0 and (buf is None or buf.dtype != img.dtype or img.size > buf.size):
                self._rgba[slot] = img  # refilled next frame (the kernels are done with it by then)
            return _ViewCtx(cam, img, None, np.asarray(cam.center, dtype=np.float64), self._r2[key], region)
        fg = erode_mask(m, (cam.height, cam.width), self.config.erode_px, self.config.mask_threshold)
        if not fg.any():
            return None
        img = np.ascontiguousarray(image[..., :3], dtype=np.uint8 if image.dtype == np.uint8 else np.float32).reshape(
            -1, 3
        )
        return _ViewCtx(cam, img, fg.ravel(), np.asarray(cam.center, dtype=np.float64), self._r2[key])

    def _zbuffer_views(
        self, vertices: np.ndarray, views: Iterable[ImageView], frame, occlusion: bool = True
    ) -> _ZFrame:
        """Texel surface and every view's checked inputs and triangle-id buffer (:mod:`gsavatar.prep.zbuffer`).

        Views are consumed one at a time and rasterized as they arrive; their images are kept (the
        fused kernel samples all views per block of texels).
        """
        # local: zbuffer imports numba (compiled kernels); every avatar-prep command imports this module
        from gsavatar.prep import zbuffer as zb

        zb.set_threads()
        v = self._check_vertices(vertices, frame)
        N = self.num_texels
        P = np.empty((3, N))
        Nrm = np.empty((3, N))
        zb.surface(v, vertex_normals(v, self.faces), self._z_corners, self._z_bary, P, Nrm)
        faces = self.faces
        out = _ZFrame(P, Nrm, 0, [], [], [], [], [])
        for view in views:
            c = out.num_views
            out.num_views += 1
            ctx = self._view_ctx(view, frame, keep_uint8=True, quad=True, slot=c)
            if ctx is None or N == 0:  # all-background mask: no samples from this view
                continue
            cam = ctx.cam
            key = _camera_key(cam)
            if key not in self._grids:
                self._grids[key] = zb.pinhole_grid(cam, ctx.r2max)
            grid = self._grids[key]
            crop = (0, 0)
            if occlusion and len(faces):
                vc = zb.transform(
                    v,
                    np.ascontiguousarray(cam.R, dtype=np.float64),
                    np.ascontiguousarray(cam.T, dtype=np.float64).reshape(3),
                )
                x0, y0, x1, y1 = _raster_crop(vc, grid)
                crop = (x0, y0)
                shape = (max(y1 - y0 + 1, 1), max(x1 - x0 + 1, 1))
                tri_id = np.full(shape, -1, np.int32)
                planes = np.empty((len(faces), 4))
                if x1 >= x0 and y1 >= y0:
                    invz = np.zeros(shape, np.float32)
                    zb.rasterize(
                        vc,
                        faces,
                        grid.fx,
                        grid.skew,
                        grid.cx - x0,
                        grid.fy,
                        grid.cy - y0,
                        ZNEAR,
                        self._closed,
                        tri_id,
                        invz,
                        planes,
                    )
            else:
                tri_id, planes = np.full((1, 1), -1, np.int32), np.zeros((1, 4))
            out.index.append(c)
            out.cams.append(zb.pack_camera(cam, float(ctx.r2max), grid, crop, ctx.region))
            out.imgs.append(ctx.image)
            out.tri_ids.append(tri_id)
            out.planes.append(planes)
        return out

    def _collect(self, vertices: np.ndarray, views: Iterable[ImageView], frame, occlusion: bool = True):
        """Per-view (rgb [N,3] float32, ok [N] bool) of every projected texel (None for views without
        foreground); the ``rays`` reference path."""
        P, Nrm = self._surface_soa(vertices, frame)
        scene = self._scene(vertices) if occlusion else None
        N = P.shape[1]
        step = self.config.chunk
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        for view in views:
            ctx = self._view_ctx(view, frame)
            if ctx is None:  # all-background mask: no samples from this view
                out.append(None)
                continue
            rgb = np.zeros((N, 3), dtype=np.float32)
            ok = np.zeros(N, dtype=bool)
            for s in range(0, N, step):
                _sample_view(
                    P[:, s : s + step],
                    Nrm[:, s : s + step],
                    ctx,
                    scene,
                    self.config,
                    rgb[s : s + step],
                    ok[s : s + step],
                )
            out.append((rgb, ok) if ok.any() else None)  # a camera that sees nothing contributes nothing
        return out

    def samples(
        self, vertices: np.ndarray, views: Iterable[ImageView], frame: int | str | None = None, occlusion: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-view samples of every projected texel (diagnostics/tests).

        -> rgb [N, C, 3] float32 (0 where unseen), ok [N, C] bool; N = :attr:`num_texels`
        in the order of :attr:`texels`, C = number of views (including ones that saw nothing).
        """
        N = self.num_texels
        if self.config.visibility == "zbuffer":
            # local: zbuffer imports numba (compiled kernels); every avatar-prep command imports this module
            from gsavatar.prep import zbuffer as zb

            zf = self._zbuffer_views(vertices, views, frame, occlusion)
            rgb = np.zeros((N, zf.num_views, 3), np.float32)
            ok = np.zeros((N, zf.num_views), bool)
            for k, c in enumerate(zf.index):
                r = np.zeros((N, 3), np.float32)
                o = np.zeros(N, bool)
                zb.sample_view(
                    zf.P,
                    zf.Nrm,
                    self._z_tri,
                    self.faces,
                    zf.cams[k],
                    zf.imgs[k],
                    zf.imgs[k].dtype == np.uint8,
                    occlusion,
                    zf.tri_ids[k],
                    zf.planes[k],
                    float(self.config.occlusion_eps),
                    float(self.config.min_cos),
                    r,
                    o,
                )
                rgb[self._zorder, c] = np.where(o[:, None], r, np.float32(0))
                ok[self._zorder, c] = o
            return rgb, ok
        got = self._collect(vertices, views, frame, occlusion)
        rgb = np.zeros((N, len(got), 3), np.float32)
        ok = np.zeros((N, len(got)), bool)
        for i, g in enumerate(got):
            if g is not None:
                rgb[:, i], ok[:, i] = g
        return rgb, ok

    def _scene(self, vertices: np.ndarray):
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        if len(self.faces):
            scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(self.faces, dtype=np.uint32)),
            )
        return scene

    def project(self, vertices: np.ndarray, views: Iterable[ImageView], frame: int | str | None = None) -> TexelFusion:
        """Fused UV texture of one frame. ``views`` may be a generator (one view's images in memory at a time).

        Raises ValueError naming ``frame`` for NaN/Inf posed vertices or mis-sized images.
        """
        cfg = self.config
        if cfg.visibility == "zbuffer":
            return self._project_zbuffer(vertices, views, frame)
        got = [g for g in self._collect(vertices, views, frame) if g is not None]
        S = self.size
        texture = np.zeros((S * S, 3), dtype=np.float32)
        count = np.zeros(S * S, dtype=np.uint8)
        seen = np.zeros(S * S, dtype=np.uint8)
        step = cfg.chunk
        if got:
            for s in range(0, self.num_texels, step):
                col, cnt, sn = _fuse_views(
                    [c[s : s + step] for c, _ in got], [o[s : s + step] for _, o in got], cfg.fusion, cfg.band
                )
                t = self.texels[s : s + step]
                texture[t] = col
                count[t] = np.minimum(cnt, 255)
                seen[t] = np.minimum(sn, 255)
        valid = count > 0
        texture[~valid] = 0.0
        return TexelFusion(texture.reshape(S, S, 3), count.reshape(S, S), seen.reshape(S, S), valid.reshape(S, S))

    def _project_zbuffer(self, vertices: np.ndarray, views: Iterable[ImageView], frame) -> TexelFusion:
        """:meth:`project` by the compiled kernels (``visibility="zbuffer"``)."""
        from numba.typed import List

        # local: zbuffer imports numba (compiled kernels); every avatar-prep command imports this module
        from gsavatar.prep import zbuffer as zb

        cfg = self.config
        zf = self._zbuffer_views(vertices, views, frame)
        N = self.num_texels
        S = self.size
        texture = np.zeros((S * S, 3), dtype=np.float32)
        count = np.zeros(S * S, dtype=np.uint8)
        seen = np.zeros(S * S, dtype=np.uint8)
        if zf.index and N:
            u8 = all(im.dtype == np.uint8 for im in zf.imgs)
            imgs = (
                zf.imgs
                if u8
                else [im if im.dtype == np.float32 else im.astype(np.float32) / np.float32(255) for im in zf.imgs]
            )
            zb.project_frame(
                zf.P,
                zf.Nrm,
                self._z_tri,
                self.faces,
                np.stack(zf.cams),
                List(imgs),
                u8,
                True,
                List(zf.tri_ids),
                List(zf.planes),
                float(cfg.occlusion_eps),
                float(cfg.min_cos),
                cfg.fusion == "median_band",
                float(cfg.band[0]),
                float(cfg.band[1]),
                BLOCK,
                self._z_texels,
                texture,
                count,
                seen,
            )
        valid = count > 0
        return TexelFusion(texture.reshape(S, S, 3), count.reshape(S, S), seen.reshape(S, S), valid.reshape(S, S))


def is_closed(faces: np.ndarray) -> bool:
    """True when every directed edge (a, b) of faces [F, 3] occurs once and its reverse (b, a) once: a closed,
    consistently oriented surface (each edge shared by exactly two triangles traversing it in opposite directions)."""
    f = np.asarray(faces, np.int64)
    if f.size == 0:
        return False
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    fwd = np.sort(e[:, 0] * n + e[:, 1])
    if np.any(fwd[1:] == fwd[:-1]):
        return False
    rev = np.sort(e[:, 1] * n + e[:, 0])
    return bool(np.array_equal(fwd, rev))


def _raster_crop(vc: np.ndarray, grid) -> tuple[int, int, int, int]:
    """Inclusive pixel box (x0, y0, x1, y1) of the grid that the mesh can cover: the projected vertices'
    bounding box plus one pixel, clipped to the grid (x1 < x0 when it misses the grid); the whole grid
    when a vertex is closer than ZNEAR (clipped triangles reach past their vertices). vc [V, 3] camera space."""
    Wg, Hg = grid.width, grid.height
    if not np.all(vc[:, 2] >= ZNEAR):
        return 0, 0, Wg - 1, Hg - 1
    x = vc[:, 0] / vc[:, 2]
    y = vc[:, 1] / vc[:, 2]
    u = grid.fx * x + grid.skew * y + grid.cx
    w = grid.fy * y + grid.cy
    x0, x1 = max(math.floor(u.min()) - 1, 0), min(math.ceil(u.max()) + 1, Wg - 1)
    y0, y1 = max(math.floor(w.min()) - 1, 0), min(math.ceil(w.max()) + 1, Hg - 1)
    return int(x0), int(y0), int(x1), int(y1)


def _morton(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Z-order (Morton) code of non-negative integer coordinates < 2^16. y, x [N] -> [N] int64."""

    def spread(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, np.int64) & 0xFFFF
        v = (v | (v << 8)) & 0x00FF00FF
        v = (v | (v << 4)) & 0x0F0F0F0F
        v = (v | (v << 2)) & 0x33333333
        return (v | (v << 1)) & 0x55555555

    return (spread(y) << 1) | spread(x)


ZNEAR = 1e-6
"""Camera-space depth (metres) below which the z-buffer clips triangles (the texel test is ``z > 1e-6`` too)."""
BLOCK = 1024
"""Texels per block of the fused z-buffer kernel (its samples, C x BLOCK x 13 bytes, stay in cache)."""


def prepare_texel_map(
    template: Template, config: ProjectConfig | None = None, cache_dir: str | Path | None = None
) -> tuple[Template, TexelMap]:
    """The template with UVs (xatlas unwrap if it has none, cached in ``cache_dir``) and its
    :class:`TexelMap` at ``config.tex_size`` with ``config.gutter_px`` seam dilation. Build once per run."""
    config = config or ProjectConfig(tex_size=512)
    if config.tex_size is None:
        raise ValueError(
            "config.tex_size is None (derived): resolve it first, e.g. with gsavatar.prep.stages.resolve_tex_size"
        )
    template = ensure_uvs(template, cache_dir)
    return template, build_texel_map(template, size=config.tex_size, gutter=config.gutter_px)


def project_uv(
    vertices: np.ndarray,
    faces: np.ndarray,
    texel_map: TexelMap,
    views: Iterable[ImageView],
    config: ProjectConfig | None = None,
    face_uv_mask: np.ndarray | None = None,
    frame: int | str | None = None,
) -> TexelFusion:
    """One-shot :meth:`UVProjector.project` (build a :class:`UVProjector` once to reuse it over frames)."""
    return UVProjector(faces, texel_map, config, face_uv_mask).project(vertices, views, frame)


# --------------------------------------------------------------------------- loading
def cameras_seeing(vertices: np.ndarray, cameras: Sequence[Camera]) -> list[str]:
    """Names of the cameras that have at least one of ``vertices`` in front of them and inside
    their image (pinhole test, distortion ignored: it is a sanity check of the calibration).

    vertices: [N, 3] world space, metres (e.g. the posed template of a few frames).
    """
    out = []
    for cam in cameras:
        pc = vertices @ cam.R.T + cam.T  # [N, 3] camera space (cam_from_world)
        pc = pc[pc[:, 2] > 1e-6]  # in front of the camera
        uv = pc[:, :2] / pc[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]  # [n, 2] pixels
        if np.any((uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)):
            out.append(cam.name)
    return out


def iter_frame_views(
    capture: Capture, frame: int, cams: Sequence[str] | None = None, uint8: bool = False
) -> Iterable[ImageView]:
    """Yield (camera, image [H,W,3] float32, mask [H,W] float32) of one frame, one view at a time.

    ``uint8``: 8-bit image files come as their uint8 values (:func:`~gsavatar.utils.io.read_image`'s
    ``keep_uint8``; the projector samples them as ``x / 255``, the same numbers)."""
    for name in cams if cams is not None else list(capture.cameras):
        if name not in capture.cameras:
            raise KeyError(f"unknown camera {name!r}")
        cam = capture.cameras[name]
        ip, mp = capture.image_path(name, frame), capture.mask_path(name, frame)
        img = read_image(ip, keep_uint8=uint8)
        mask = read_mask(mp)
        if img.shape[:2] != (cam.height, cam.width):
            raise SchemaError(
                ip,
                "size",
                f"is {img.shape[1]}x{img.shape[0]}, calibration.json says {cam.width}x{cam.height} for {name!r}",
            )
        if mask.shape[:2] != (cam.height, cam.width):
            raise SchemaError(
                mp,
                "size",
                f"is {mask.shape[1]}x{mask.shape[0]}, calibration.json says {cam.width}x{cam.height} for {name!r}",
            )
        warn_mask_coverage(mp, mask)
        yield cam, img, mask


MIN_FOREGROUND = 1e-4
"""A mask with less than this fraction of foreground pixels counts as empty (warning per view)."""
MAX_FOREGROUND = 0.98
"""A mask with more than this fraction of foreground counts as full (no background: warning per view)."""


def mask_coverage(mask: np.ndarray) -> float:
    """Fraction of pixels with foreground > 0.5.  mask [H, W] in [0, 1]"""
    return float((mask > 0.5).mean()) if mask.size else 0.0


def warn_mask_coverage(path, mask: np.ndarray) -> str | None:
    """Print (and return) a warning for an empty or full mask."""
    c = mask_coverage(mask)
    msg = None
    if c < MIN_FOREGROUND:
        msg = f"warning: {path}: no foreground ({100 * c:.3f}% of pixels > 0.5)"
    elif c > MAX_FOREGROUND:
        msg = f"warning: {path}: {100 * c:.1f}% foreground (no background: is the mask inverted or in another channel?)"
    if msg:
        print(msg)
    return msg


def preflight_frames(num_frames: int, max_frames: int) -> list[int]:
    """Up to ``max_frames`` evenly spaced frame indices of ``[0, num_frames)``: what the pre-projection checks read."""
    return sorted({int(f) for f in np.linspace(0, num_frames - 1, min(max_frames, num_frames)).round()})


def check_mask_coverage(capture: Capture, cams: Sequence[str], max_frames: int = 8, min_ok: float = 0.5) -> None:
    """Refuse a capture whose masks are (almost) all empty or all full, before anything is projected.

    Reads the masks of ``cams`` in up to ``max_frames`` evenly spaced frames; if fewer than ``min_ok``
    of them have between MIN_FOREGROUND and MAX_FOREGROUND foreground, the textures would be empty (or
    full of background): SchemaError naming the masks folder, with examples. Single odd views only warn.
    """
    frames = preflight_frames(capture.num_frames, max_frames)
    bad: list[str] = []
    n = 0
    for f in frames:
        for name in cams:
            p = capture.mask_path(name, f)
            c = mask_coverage(read_mask(p))
            n += 1
            if not MIN_FOREGROUND <= c <= MAX_FOREGROUND:
                bad.append(f"{p.relative_to(capture.root)} ({100 * c:.2f}%)")
    if n and (n - len(bad)) / n < min_ok:
        raise SchemaError(
            capture.root / "masks",
            "",
            f"{len(bad)} of {n} sampled masks are empty or all foreground, "
            f"e.g. {', '.join(bad[:3])}: the textures would be empty or background; masks must be white "
            "(or 1, or the alpha) on the body and 0 elsewhere (docs/data_schema.md, Masks)",
        )


def load_frame_views(
    capture: Capture, frame: int, cams: Sequence[str] | None = None, uint8: bool = False
) -> list[ImageView]:
    """All views of one frame: list of (camera, image [H,W,3] float32 [0,1], mask [H,W] float32 [0,1])
    (``uint8``: as :func:`iter_frame_views`)."""
    return list(iter_frame_views(capture, frame, cams, uint8))


def prefetched_frame_views(
    capture: Capture, frames: Sequence[int], cams: Sequence[str] | None = None, uint8: bool = False, ahead: bool = True
) -> Iterator[tuple[int, list[ImageView]]]:
    """(frame, :func:`load_frame_views`) for each of ``frames``, reading the next frame in a background thread
    while the caller works on the current one (``ahead``; OpenCV's decoders and the z-buffer kernels release
    the GIL, so on two cores reading overlaps projection). At most two frames' views are in memory. A reading
    error is raised when its frame is reached, as without prefetching; a consumer that stops early leaves at
    most one read running, which finishes and is dropped."""
    frames = list(frames)
    if not ahead or len(frames) < 2:
        for f in frames:
            yield f, load_frame_views(capture, f, cams, uint8)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gsavatar-read") as pool:
        nxt = pool.submit(load_frame_views, capture, frames[0], cams, uint8)
        for k, f in enumerate(frames):
            views = nxt.result()
            nxt = pool.submit(load_frame_views, capture, frames[k + 1], cams, uint8) if k + 1 < len(frames) else None
            yield f, views
            views = None
