"""Compiled (numba) kernels of the z-buffer UV projection path (:mod:`gsavatar.prep.project_uv`).

The kernels, each with a naive oracle in the tests:

- :func:`rasterize` -- per view, a triangle-id buffer of the posed mesh on a *pinhole* grid
  (undistorted normalised coordinates mapped with the camera's focal lengths; lens distortion
  moves where a ray lands on the sensor, never which surface it hits first, so visibility is
  decided before distortion). Pixel centres at integer grid coordinates, nearest surface by
  perspective-correct ``1/z``, near-plane clipping, no back-face culling (an open mesh's back
  faces occlude, as in the ray path). Serial over triangles: ties keep the first triangle,
  so the buffer is deterministic.
- :func:`sample_view` -- per view, every texel: in front, facing (``min_cos``), inside the
  distortion's valid radius and the image, 4 bilinear taps in the eroded mask (the alpha channel of
  the RGBA buffer of the mask's bounding region, :func:`region_rgba`), visible in the
  buffer (see below), bilinear colour. Same tests and same float64/float32 arithmetic
  as ``project_uv._sample_view`` (the numpy/open3d reference). In two passes per block of texels:
  :func:`_project_block` (projection and the geometric tests, branch-free so LLVM vectorises it) and
  :func:`_sample_block` (mask, depth test and taps for the texels pass 1 kept).
- :func:`fuse` -- per texel, the median-band (or mean) fusion over views, same rule and same
  float64 accumulation order as ``project_uv.fuse_samples``.
- :func:`project_frame` -- both, per block of texels over all views; a (block, view) pair is skipped
  when a bound on the block (bounding sphere and normal cone, :func:`_faces_away`) proves that no texel
  faces the camera. Equal, bit for bit, to :func:`sample_view` + :func:`fuse` (tested).

Depth test: the texel's pinhole grid coordinate is rounded to the nearest grid pixel; that
pixel's front triangle ``t`` is read. The texel is visible when ``t`` is empty, the texel's
own triangle or one sharing a vertex with it (on a coarse mesh a neighbour facet's plane,
extrapolated to the texel, passes up to several mm in front of it at oblique views: measured
2.7 % false occlusions on a 24-segment sphere without this rule, the ray path has none), else when the
depth of ``t``'s *plane* along the texel's exact ray is not in front
of the texel by more than ``eps`` (metres along the ray, like the ray path's offset start):
``z_texel * (1 - eps / dist) <= z_plane``. Evaluating the plane on the texel's own ray, not the
pixel-centre depth, removes the half-pixel slope error at oblique angles. Differences from
the ray path are confined to sub-pixel neighbourhoods of occluding contours (the nearest pixel's
triangle decides) and to sub-``eps`` gaps.

Packed rows: a view's camera reaches the kernels as one float64 row (:func:`pack_camera`) and a block's
bounds as another (:func:`_block_bounds`); both are laid out by a table of named fields (:data:`CAMERA_ROW`,
:data:`BOUNDS_ROW`) whose offsets are module constants (``cp[CAM_FX]``, ``bnd[BND_RADIUS]``), compile-time
constants to numba.

Threads: the per-texel kernels use ``prange``; :func:`set_threads` caps numba at
``min(torch threads, numba threads)`` so OMP_NUM_THREADS=1 means one thread. Per-texel results
do not depend on the thread count (no reductions across texels).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from gsavatar.data_schema.capture import Camera
from gsavatar.geometry.camera import distort, undistort

from gsavatar.utils.compiled import CACHE, set_threads  # noqa: F401  (threads and threading layer: one place)


# --------------------------------------------------------------------------- grid


class Grid(NamedTuple):
    """Pinhole depth grid of a camera: ``(u, v) = (fx x + skew y + cx, fy y + cy)`` of undistorted
    normalised coordinates (x, y); pixel centres at integers, ``width x height`` pixels."""

    fx: float
    skew: float
    cx: float
    fy: float
    cy: float
    width: int
    height: int

    @property
    def params(self) -> np.ndarray:
        """(fx, skew, cx, fy, cy). -> [5] float64"""
        return np.array([self.fx, self.skew, self.cx, self.fy, self.cy], np.float64)


MAX_GRID_SCALE = 3
"""A distorted camera's grid is at most this many times the image size per side."""


def pinhole_grid(cam: Camera, r2max: float) -> Grid:
    """The grid :func:`rasterize` uses for ``cam``.

    Without distortion: the image itself (the camera's K). With distortion: the camera's focal
    lengths and skew, shifted and sized to cover the undistorted image (bounding box of the
    undistorted border, limited to the radius ``sqrt(r2max)`` beyond which texels are rejected
    anyway) plus a 2-pixel margin, capped at :data:`MAX_GRID_SCALE` x the image per side.
    """
    K = np.asarray(cam.K, np.float64)
    fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    W, H = int(cam.width), int(cam.height)
    d = np.asarray(cam.dist, np.float64)
    if not np.any(d):
        return Grid(fx, skew, cx, fy, cy, W, H)
    t = np.linspace(0, 1, 257)
    border = np.concatenate(
        [
            np.stack([t * (W - 1), np.zeros_like(t)], 1),
            np.stack([t * (W - 1), np.full_like(t, H - 1)], 1),
            np.stack([np.zeros_like(t), t * (H - 1)], 1),
            np.stack([np.full_like(t, W - 1), t * (H - 1)], 1),
        ]
    )
    xd = (border - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    xn = undistort(xd, d, iters=50)
    good = (np.abs(distort(xn, d) - xd).max(axis=1) < 1e-4) & np.all(np.isfinite(xn), axis=1)
    if good.any():
        lo, hi = xn[good].min(0), xn[good].max(0)
    else:  # no convergence: fall back to the distorted extent, widened
        lo, hi = xd.min(0) * 1.5, xd.max(0) * 1.5
    if np.isfinite(r2max):
        r = math.sqrt(r2max)
        lo, hi = np.maximum(lo, -r), np.minimum(hi, r)
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]])
    u = fx * corners[:, 0] + skew * corners[:, 1]
    v = fy * corners[:, 1]
    u0, u1 = max(u.min() - 2, cx - MAX_GRID_SCALE * W / 2), min(u.max() + 2, cx + MAX_GRID_SCALE * W / 2)
    v0, v1 = max(v.min() - 2, cy - MAX_GRID_SCALE * H / 2), min(v.max() + 2, cy + MAX_GRID_SCALE * H / 2)
    if not (u1 > u0 and v1 > v0):
        return Grid(fx, skew, cx, fy, cy, W, H)
    return Grid(
        fx,
        skew,
        -math.floor(u0),
        fy,
        -math.floor(v0),
        int(math.ceil(u1) - math.floor(u0)) + 1,
        int(math.ceil(v1) - math.floor(v0)) + 1,
    )


_U8_TO_FLOAT = np.arange(256, dtype=np.float32) / np.float32(255)
"""``float32(x) / 255`` for every 8-bit value (the u8 sampling path reads it instead of dividing)."""


# --------------------------------------------------------------------------- masks


def quad_foreground(
    mask: np.ndarray | None, shape: tuple[int, int], erode_px: int, threshold: float = 0.5
) -> np.ndarray:
    """Pixels whose four bilinear taps (x..x+1, y..y+1) all lie in the eroded foreground. -> [H, W] bool

    ``E = erode(mask > threshold, erode_px x erode_px)`` (as ``project_uv.erode_mask``, out-of-image
    pixels count as foreground), then ``E[y,x] & E[y,x+1] & E[y+1,x] & E[y+1,x+1]``, computed as one
    erosion with an (e+1) x (e+1) kernel anchored at (e//2, e//2): one tap per texel and view instead of four.
    """
    if mask is None:
        return np.ones(shape, dtype=bool)
    return _quad_erode(np.asarray(mask) > threshold, erode_px)


def _quad_erode(fg: np.ndarray, erode_px: int) -> np.ndarray:
    """:func:`quad_foreground` of a thresholded mask fg [h, w] bool (pixels outside it count as foreground)."""
    import cv2

    e = erode_px if erode_px > 1 else 1
    return cv2.erode(
        np.ascontiguousarray(fg).view(np.uint8),
        np.ones((e + 1, e + 1), np.uint8),
        anchor=(e // 2, e // 2),
        borderType=cv2.BORDER_CONSTANT,
        borderValue=1,
    ).view(bool)


def foreground_box(fg: np.ndarray | None, shape: tuple[int, int], erode_px: int) -> tuple[int, int, int, int] | None:
    """The image region the sampling kernels need: the bounding box of the thresholded mask fg [H, W] bool
    widened by ``max(erode_px, 1) + 1`` pixels, clipped to the image, as (x0, y0, width, height); the whole
    image without a mask (None); None when nothing is foreground.

    Exact: every pixel whose :func:`quad_foreground` flag is set lies in the foreground's bounding box
    (the (e+1)^2 window contains the pixel itself), and within that box the flag only reads pixels up to
    ``e`` away, so :func:`quad_foreground` of the region equals that of the whole image there (tested).
    """
    H, W = shape
    if fg is None:
        return 0, 0, W, H
    import cv2

    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(fg).view(np.uint8))
    if w == 0 or h == 0:
        return None
    m = (erode_px if erode_px > 1 else 1) + 1
    x0, y0 = max(x - m, 0), max(y - m, 0)
    x1, y1 = min(x + w + m, W), min(y + h + m, H)
    return x0, y0, x1 - x0, y1 - y0


def image_with_foreground(image: np.ndarray, fg: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The view as the sampling kernels read it: RGB plus the :func:`quad_foreground` flag as a fourth
    channel (1 or 0), so the mask test reads the cache line the first bilinear tap needs anyway
    (measured: ~12% of :func:`project_frame` at 1024^2 on a THuman4.0-sized capture, against a separate
    [H*W] mask array). image [H, W, 3] uint8 or float32, fg [H, W] bool -> [H*W, 4] of image's dtype

    ``out``: an array of that dtype with at least H*W*4 elements to fill (reused across frames: a fresh 6 MB
    array per view costs its page faults every frame); ignored when too small."""
    import cv2

    H, W = fg.shape
    img = image[..., :3]
    if img.strides[2] != img.itemsize or img.strides[1] != 3 * img.itemsize:  # OpenCV takes strided rows, not pixels
        img = np.ascontiguousarray(img)
    if out is None or out.size < H * W * 4 or out.dtype != img.dtype or not out.flags.c_contiguous:
        out = np.empty((H * W, 4), img.dtype)
    out = out.reshape(-1)[: H * W * 4].reshape(H * W, 4)
    o = out.reshape(H, W, 4)
    cv2.cvtColor(img, cv2.COLOR_RGB2RGBA, dst=o)  # copies RGB, alpha = max value
    if img.dtype == np.uint8:
        cv2.mixChannels([np.ascontiguousarray(fg).view(np.uint8)], [o], [0, 3])
    else:
        np.copyto(o[..., 3], fg, casting="unsafe")
    return out


def region_rgba(
    image: np.ndarray, mask: np.ndarray | None, erode_px: int, threshold: float = 0.5, out: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
    """:func:`image_with_foreground` of the :func:`foreground_box` region only. image [H, W, 3], mask [H, W]
    -> (rgba [w*h, 4], (x0, y0, w, h)), or None when the mask has no foreground. The kernels treat every
    pixel outside the region as background (its flag is 0 in the whole-image computation)."""
    H, W = image.shape[:2]
    fg = None if mask is None else np.asarray(mask) > threshold
    box = foreground_box(fg, (H, W), erode_px)
    if box is None:
        return None
    x0, y0, w, h = box
    if fg is None:
        quad = np.ones((h, w), bool)
    else:
        quad = _quad_erode(fg[y0 : y0 + h, x0 : x0 + w], erode_px)
        # the region's own border counts as foreground in the erosion; where it is the image's border that is
        # the whole-image rule, and elsewhere the margin keeps it more than e pixels from any foreground
    return image_with_foreground(image[y0 : y0 + h, x0 : x0 + w], quad, out), box


# --------------------------------------------------------------------------- rasterizer


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _raster_tri(ax, ay, az, bx, by, bz, cx, cy, cz, tri, gfx, gskew, gcx, gfy, gcy, tri_id, invz):
    """Rasterize one camera-space triangle (all z > 0) into tri_id [H, W] int32 / invz [H, W] float64."""
    H, W = tri_id.shape
    iza, izb, izc = 1.0 / az, 1.0 / bz, 1.0 / cz
    xa, ya = ax * iza, ay * iza
    xb, yb = bx * izb, by * izb
    xc, yc = cx * izc, cy * izc
    sax, say = gfx * xa + gskew * ya + gcx, gfy * ya + gcy
    sbx, sby = gfx * xb + gskew * yb + gcx, gfy * yb + gcy
    scx, scy = gfx * xc + gskew * yc + gcx, gfy * yc + gcy
    area = (sbx - sax) * (scy - say) - (sby - say) * (scx - sax)
    if not (abs(area) > 1e-12):
        return
    x0 = max(int(math.ceil(min(sax, sbx, scx))), 0)
    x1 = min(int(math.floor(max(sax, sbx, scx))), W - 1)
    y0 = max(int(math.ceil(min(say, sby, scy))), 0)
    y1 = min(int(math.floor(max(say, sby, scy))), H - 1)
    if x0 > x1 or y0 > y1:
        return
    s = 1.0 if area > 0 else -1.0
    inv_area = 1.0 / abs(area)
    for y in range(y0, y1 + 1):
        py = float(y)
        for x in range(x0, x1 + 1):
            px = float(x)
            w0 = s * ((scx - sbx) * (py - sby) - (scy - sby) * (px - sbx))
            w1 = s * ((sax - scx) * (py - scy) - (say - scy) * (px - scx))
            w2 = s * ((sbx - sax) * (py - say) - (sby - say) * (px - sax))
            if w0 >= 0 and w1 >= 0 and w2 >= 0:
                iz = (w0 * iza + w1 * izb + w2 * izc) * inv_area
                if iz > invz[y, x]:
                    invz[y, x] = iz
                    tri_id[y, x] = tri


@numba.njit(cache=CACHE, error_model="numpy", nogil=True)
def rasterize(vc, faces, gfx, gskew, gcx, gfy, gcy, znear, cull_back, tri_id, invz, planes):
    """Triangle-id buffer of a camera-space mesh.

    vc [V, 3] float64 camera-space vertices (cam_from_world applied), faces [F, 3] int,
    grid: ``(u, v) = (gfx x/z + gskew y/z + gcx, gfy y/z + gcy)``, pixel centres at integers.
    Writes tri_id [H, W] int32 (-1 = empty; fill with -1 first), invz [H, W] float32/64 scratch (1/z of the
    front surface, 0 = empty; fill with 0 first) and planes [F, 4] float64: camera-space plane
    ``n . X = d`` of every triangle (n unnormalised). Parts with z < znear are clipped away.
    ``cull_back``: skip triangles facing away from the camera (``d >= 0``; exact for a closed,
    outward-oriented mesh seen from outside: a ray's first hit enters the surface, so it is front-facing).
    """
    F = faces.shape[0]
    px = np.empty(4)
    py = np.empty(4)
    pz = np.empty(4)
    for f in range(F):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = vc[i0, 0], vc[i0, 1], vc[i0, 2]
        bx, by, bz = vc[i1, 0], vc[i1, 1], vc[i1, 2]
        cx, cy, cz = vc[i2, 0], vc[i2, 1], vc[i2, 2]
        e1x, e1y, e1z = bx - ax, by - ay, bz - az
        e2x, e2y, e2z = cx - ax, cy - ay, cz - az
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        planes[f, 0], planes[f, 1], planes[f, 2] = nx, ny, nz
        planes[f, 3] = nx * ax + ny * ay + nz * az
        if cull_back and planes[f, 3] >= 0:
            continue
        n_in = (az >= znear) + (bz >= znear) + (cz >= znear)
        if n_in == 3:
            _raster_tri(ax, ay, az, bx, by, bz, cx, cy, cz, f, gfx, gskew, gcx, gfy, gcy, tri_id, invz)
            continue
        if n_in == 0:
            continue
        # Sutherland-Hodgman against z >= znear: a triangle or a quad (fan-triangulated)
        m = 0
        for k in range(3):
            j = (k + 1) % 3
            ix, iy, iz = vc[faces[f, k], 0], vc[faces[f, k], 1], vc[faces[f, k], 2]
            jx, jy, jz = vc[faces[f, j], 0], vc[faces[f, j], 1], vc[faces[f, j], 2]
            if iz >= znear:
                px[m], py[m], pz[m] = ix, iy, iz
                m += 1
            if (iz >= znear) != (jz >= znear):
                t = (znear - iz) / (jz - iz)
                px[m], py[m], pz[m] = ix + t * (jx - ix), iy + t * (jy - iy), znear
                m += 1
        for k in range(1, m - 1):
            _raster_tri(
                px[0],
                py[0],
                pz[0],
                px[k],
                py[k],
                pz[k],
                px[k + 1],
                py[k + 1],
                pz[k + 1],
                f,
                gfx,
                gskew,
                gcx,
                gfy,
                gcy,
                tri_id,
                invz,
            )


@numba.njit(cache=CACHE, error_model="numpy", nogil=True)
def transform(vertices, R, T):
    """Camera-space vertices ``R v + T``. vertices [V, 3] float64 -> [V, 3] float64 (no BLAS)."""
    V = vertices.shape[0]
    out = np.empty((V, 3))
    for i in range(V):
        x, y, z = vertices[i, 0], vertices[i, 1], vertices[i, 2]
        for k in range(3):
            out[i, k] = R[k, 0] * x + R[k, 1] * y + R[k, 2] * z + T[k]
    return out


# --------------------------------------------------------------------------- packed rows


class RowField(NamedTuple):
    """One field of a packed float64 row that the kernels read at ``offset`` (its module constant)."""

    name: str  # the constant is PREFIX_<name>, e.g. CAM_FX
    offset: int  # first element in the row
    width: int  # number of elements
    doc: str  # meaning and units


class _RowLayout:
    """Lays out a packed row field by field, in call order: each field starts where the previous one ended,
    so the offsets are contiguous and non-overlapping by construction (and tested)."""

    def __init__(self) -> None:
        self.fields: list[RowField] = []
        self.size = 0

    def field(self, name: str, doc: str, width: int = 1) -> int:
        """Append a field; -> its offset."""
        self.fields.append(RowField(name, self.size, width, doc))
        self.size += width
        return self.fields[-1].offset


def _pack_row(fields: tuple[RowField, ...], size: int, values: dict[str, object]) -> np.ndarray:
    """A [size] float64 row holding values[f.name] at each field's offset; exactly the fields' names."""
    if set(values) != {f.name for f in fields}:
        raise ValueError(f"row fields must be {[f.name for f in fields]}, got {sorted(values)}")
    row = np.empty(size, np.float64)
    for f in fields:
        row[f.offset : f.offset + f.width] = values[f.name]
    return row


# One view's camera, as :func:`pack_camera` writes it and the kernels (:func:`_project_block`,
# :func:`_sample_block`, :func:`_faces_away`) read it: ``cp[CAM_FX]``. Numba reads module-level ints as
# compile-time constants, so a named index costs what a literal did. A new field is one line here (plus
# its value in pack_camera); the offsets of all later fields follow. Integer-valued fields (sizes, pixel
# offsets) and flags (1.0 / 0.0) are stored as float64 like the rest.
_cam = _RowLayout()
CAM_R00 = _cam.field("R00", "cam_from_world rotation R[0, 0]: X_cam = R X_world + T (OpenCV axes, +z forward)")
CAM_R01 = _cam.field("R01", "R[0, 1]")
CAM_R02 = _cam.field("R02", "R[0, 2]")
CAM_R10 = _cam.field("R10", "R[1, 0]")
CAM_R11 = _cam.field("R11", "R[1, 1]")
CAM_R12 = _cam.field("R12", "R[1, 2]")
CAM_R20 = _cam.field("R20", "R[2, 0]")
CAM_R21 = _cam.field("R21", "R[2, 1]")
CAM_R22 = _cam.field("R22", "R[2, 2]")
CAM_T0 = _cam.field("T0", "cam_from_world translation T[0] (metres)")
CAM_T1 = _cam.field("T1", "T[1] (metres)")
CAM_T2 = _cam.field("T2", "T[2] (metres)")
CAM_CENTER_X = _cam.field("CENTER_X", "camera centre -R^T T, world x (metres)")
CAM_CENTER_Y = _cam.field("CENTER_Y", "camera centre, world y (metres)")
CAM_CENTER_Z = _cam.field("CENTER_Z", "camera centre, world z (metres)")
CAM_FX = _cam.field("FX", "K[0, 0], focal length in x (pixels)")
CAM_SKEW = _cam.field("SKEW", "K[0, 1], skew (pixels)")
CAM_CX = _cam.field("CX", "K[0, 2], principal point x (pixels, pixel centres at integers)")
CAM_FY = _cam.field("FY", "K[1, 1], focal length in y (pixels)")
CAM_CY = _cam.field("CY", "K[1, 2], principal point y (pixels)")
CAM_K1 = _cam.field("K1", "radial distortion k1 (OpenCV order k1, k2, p1, p2, k3; unitless)")
CAM_K2 = _cam.field("K2", "radial distortion k2")
CAM_P1 = _cam.field("P1", "tangential distortion p1")
CAM_P2 = _cam.field("P2", "tangential distortion p2")
CAM_K3 = _cam.field("K3", "radial distortion k3")
CAM_USE_DIST = _cam.field("USE_DIST", "1.0 when any distortion coefficient is non-zero, else 0.0")
CAM_R2MAX = _cam.field("R2MAX", "largest valid squared undistorted radius x^2 + y^2 (normalised; inf: any)")
CAM_WIDTH = _cam.field("WIDTH", "image width W (pixels)")
CAM_HEIGHT = _cam.field("HEIGHT", "image height H (pixels)")
CAM_GRID_FX = _cam.field("GRID_FX", "pinhole depth grid (:class:`Grid`) fx (pixels)")
CAM_GRID_SKEW = _cam.field("GRID_SKEW", "grid skew (pixels)")
CAM_GRID_CX = _cam.field("GRID_CX", "grid cx (grid pixels)")
CAM_GRID_FY = _cam.field("GRID_FY", "grid fy (pixels)")
CAM_GRID_CY = _cam.field("GRID_CY", "grid cy (grid pixels)")
CAM_GRID_WIDTH = _cam.field("GRID_WIDTH", "grid width (pixels)")
CAM_GRID_HEIGHT = _cam.field("GRID_HEIGHT", "grid height (pixels)")
CAM_CROP_X = _cam.field("CROP_X", "x of the triangle-id buffer's crop origin in the grid (grid pixels)")
CAM_CROP_Y = _cam.field("CROP_Y", "y of the crop origin (grid pixels)")
CAM_GRID_IS_IMAGE = _cam.field("GRID_IS_IMAGE", "1.0 when the grid is the image (no distortion, grid = K), else 0.0")
CAM_REGION_X = _cam.field("REGION_X", "x0 of the image region the RGBA buffer holds (:func:`region_rgba`; pixels)")
CAM_REGION_Y = _cam.field("REGION_Y", "y0 of the region (pixels)")
CAM_REGION_WIDTH = _cam.field("REGION_WIDTH", "region width (pixels; the RGBA buffer's row stride)")
CAM_REGION_HEIGHT = _cam.field("REGION_HEIGHT", "region height (pixels)")
CAM_SIZE = _cam.size
"""Length of a packed camera row (:func:`pack_camera`)."""
CAMERA_ROW: tuple[RowField, ...] = tuple(_cam.fields)
"""The camera row's fields in order (name, offset, width, doc); ``CAM_<name>`` is each one's offset."""
del _cam


def pack_camera(
    cam: Camera,
    r2max: float,
    grid: Grid,
    crop: tuple[int, int] = (0, 0),
    region: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """One view's parameters for the kernels, laid out by :data:`CAMERA_ROW`. -> [CAM_SIZE] float64

    Args:
        cam: the view's camera (K, R, T, dist, width, height)
        r2max: largest valid squared undistorted radius (``inf``: no limit)
        grid: its pinhole depth grid (:func:`pinhole_grid`)
        crop: (x, y) origin of the triangle-id buffer in the grid (grid pixels)
        region: (x0, y0, width, height) of the image region the RGBA buffer holds (:func:`region_rgba`;
            default the whole image)
    """
    K = np.asarray(cam.K, np.float64)
    R = np.asarray(cam.R, np.float64).reshape(3, 3)
    T = np.asarray(cam.T, np.float64).reshape(3)
    centre = np.asarray(cam.center, np.float64).reshape(3)
    d = np.asarray(cam.dist, np.float64).reshape(5)
    same = (not np.any(d)) and grid.params.tolist() == [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]]
    rx0, ry0, rw, rh = (0, 0, cam.width, cam.height) if region is None else region
    values = {f"R{i}{j}": R[i, j] for i in range(3) for j in range(3)}
    values.update(T0=T[0], T1=T[1], T2=T[2], CENTER_X=centre[0], CENTER_Y=centre[1], CENTER_Z=centre[2])
    values.update(FX=K[0, 0], SKEW=K[0, 1], CX=K[0, 2], FY=K[1, 1], CY=K[1, 2])
    values.update(K1=d[0], K2=d[1], P1=d[2], P2=d[3], K3=d[4], USE_DIST=float(np.any(d)), R2MAX=r2max)
    values.update(WIDTH=cam.width, HEIGHT=cam.height)
    values.update(GRID_FX=grid.fx, GRID_SKEW=grid.skew, GRID_CX=grid.cx, GRID_FY=grid.fy, GRID_CY=grid.cy)
    values.update(GRID_WIDTH=grid.width, GRID_HEIGHT=grid.height, CROP_X=crop[0], CROP_Y=crop[1])
    values.update(GRID_IS_IMAGE=float(same), REGION_X=rx0, REGION_Y=ry0, REGION_WIDTH=rw, REGION_HEIGHT=rh)
    return _pack_row(CAMERA_ROW, CAM_SIZE, values)


# --------------------------------------------------------------------------- per-texel sampling


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _adjacent(faces, a, b):
    """Triangles a and b share a vertex (faces [F, 3])."""
    for i in range(3):
        for j in range(3):
            if faces[a, i] == faces[b, j]:
                return True
    return False


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _project_block(P, Nrm, s0, n, cp, min_cos, Hc, Wc, I00, FX, FY, RAY, TI):
    """Pass 1 of a block of texels s0 .. s0+n-1 in one view: branch-free, so LLVM vectorises it. Same float64
    operations, in the same order, as the numpy reference ``project_uv._sample_view``.

    Args:
        P, Nrm: [3, N] float64 texel points / unit normals (world)
        s0, n: the block's first texel and its number of texels
        cp: [CAM_SIZE] float64 the view's packed camera (:data:`CAMERA_ROW`)
        min_cos: facing threshold on cos(normal, direction to the camera)
        Hc, Wc: shape of the view's triangle-id crop (grid pixels)
        I00: [>= n] int64 out: the RGBA-buffer index of the first bilinear tap (-1: behind the camera, not
            facing it, outside the distortion's valid radius, the image or the buffer's region)
        FX, FY: [>= n] float32 out: the tap fractions in x and y
        RAY: [>= n, 4] float64 out: (camera-space z, xu, yu, distance to the camera centre), xu, yu the
            undistorted normalised coordinates
        TI: [>= n] int64 out: the flat index into the triangle-id crop [Hc, Wc] (-1: outside it, nothing
            rasterized; -2: outside the pinhole grid, rejected)
    """
    R00, R01, R02 = cp[CAM_R00], cp[CAM_R01], cp[CAM_R02]
    R10, R11, R12 = cp[CAM_R10], cp[CAM_R11], cp[CAM_R12]
    R20, R21, R22 = cp[CAM_R20], cp[CAM_R21], cp[CAM_R22]
    T0, T1, T2 = cp[CAM_T0], cp[CAM_T1], cp[CAM_T2]
    C0, C1, C2 = cp[CAM_CENTER_X], cp[CAM_CENTER_Y], cp[CAM_CENTER_Z]
    fx, sk, cx, fy, cy = cp[CAM_FX], cp[CAM_SKEW], cp[CAM_CX], cp[CAM_FY], cp[CAM_CY]
    k1, k2, p1, p2, k3 = cp[CAM_K1], cp[CAM_K2], cp[CAM_P1], cp[CAM_P2], cp[CAM_K3]
    use_dist = cp[CAM_USE_DIST] != 0
    r2max = cp[CAM_R2MAX]
    W = int(cp[CAM_WIDTH])
    H = int(cp[CAM_HEIGHT])
    gfx, gsk, gcx = cp[CAM_GRID_FX], cp[CAM_GRID_SKEW], cp[CAM_GRID_CX]
    gfy, gcy = cp[CAM_GRID_FY], cp[CAM_GRID_CY]
    gW, gH = cp[CAM_GRID_WIDTH], cp[CAM_GRID_HEIGHT]
    ox = int(cp[CAM_CROP_X])
    oy = int(cp[CAM_CROP_Y])
    same = cp[CAM_GRID_IS_IMAGE] != 0
    rx0 = int(cp[CAM_REGION_X])
    ry0 = int(cp[CAM_REGION_Y])
    rw = int(cp[CAM_REGION_WIDTH])
    rh = int(cp[CAM_REGION_HEIGHT])
    Wm = W - 1
    Hm = H - 1
    xmax = max(W - 2, 0)
    ymax = max(H - 2, 0)
    for j in range(n):
        i = s0 + j
        X, Y, Z = P[0, i], P[1, i], P[2, i]
        z = R20 * X + R21 * Y + R22 * Z + T2
        tx, ty, tz = C0 - X, C1 - Y, C2 - Z
        nt = Nrm[0, i] * tx + Nrm[1, i] * ty + Nrm[2, i] * tz
        d = math.sqrt(tx * tx + ty * ty + tz * tz)
        xu = (R00 * X + R01 * Y + R02 * Z + T0) / z
        yu = (R10 * X + R11 * Y + R12 * Z + T1) / z
        r2 = xu * xu + yu * yu
        xn, yn = xu, yu
        if use_dist:
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xn = xu * radial + 2 * p1 * xu * yu + p2 * (r2 + 2 * xu * xu)
            yn = yu * radial + p1 * (r2 + 2 * yu * yu) + 2 * p2 * xu * yu
        px = fx * xn + sk * yn + cx
        py = fy * yn + cy
        # min_cos >= 0 also asks nt >= 0: implied, as d >= 0
        ok = (z > 1e-6) & (nt >= min_cos * d) & (r2 <= r2max) & (px >= 0) & (px <= Wm) & (py >= 0) & (py <= Hm)
        pxs = px if ok else 0.0
        pys = py if ok else 0.0
        x0 = min(int(pxs), xmax)
        y0 = min(int(pys), ymax)
        bx = x0 - rx0
        by = y0 - ry0
        inr = (bx >= 0) & (bx < rw) & (by >= 0) & (by < rh)
        I00[j] = by * rw + bx if ok & inr else -1
        FX[j] = np.float32(pxs - x0)
        FY[j] = np.float32(pys - y0)
        RAY[j, 0] = z
        RAY[j, 1] = xu
        RAY[j, 2] = yu
        RAY[j, 3] = d
        if same:  # grid == image
            gx = math.floor(pxs + 0.5)
            gy = math.floor(pys + 0.5)
            ing = True
        else:
            gx = math.floor(gfx * xu + gsk * yu + gcx + 0.5)
            gy = math.floor(gfy * yu + gcy + 0.5)
            ing = (gx >= 0) & (gx < gW) & (gy >= 0) & (gy < gH)  # outside only past MAX_GRID_SCALE
        ix = int(gx if ok & ing else 0.0) - ox
        iy = int(gy if ok & ing else 0.0) - oy
        inc = (ix >= 0) & (ix < Wc) & (iy >= 0) & (iy < Hc)  # outside the crop: nothing rasterized there
        TI[j] = (iy * Wc + ix if inc else -1) if ing else -2


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _sample_block(
    s0, n, own_tri, faces, cp, img, u8, use_vis, tid, planes, eps, I00, FX, FY, RAY, TI, out, row0, stride, k
):
    """Pass 2 of a block in one view: for each texel j that pass 1 kept, the mask flag (the RGBA buffer's
    alpha), the depth test against the triangle-id buffer (module docstring) and the bilinear colour,
    written to out[row0 + j * stride + k[j], 0:3] (float32); k[j] += 1 when seen with a finite colour.

    Args:
        s0, n: the block's first texel and its number of texels
        own_tri: [N] int32 each texel's triangle (of faces)
        faces: [F, 3] int mesh triangles (vertex ids)
        cp: [CAM_SIZE] float64 the view's packed camera (:data:`CAMERA_ROW`): the image size and the buffer
            region give the offsets of the right and lower taps (0 on a one-pixel-wide / -high image)
        img: [w*h, 4] uint8 or float32 the view's :func:`region_rgba` buffer (alpha: the quad foreground flag)
        u8: img is uint8 (read as ``x / 255``)
        use_vis: run the depth test
        tid: [Hc, Wc] int32 the view's triangle-id crop (-1 empty)
        planes: [F, 4] float64 camera-space triangle planes ``n . X = d`` (:func:`rasterize`)
        eps: depth-test tolerance along the ray (metres)
        I00, FX, FY, RAY, TI: pass 1's outputs (:func:`_project_block`)
        out: [M, 3] float32 out: the samples
        row0, stride: texel j's samples start at row ``row0 + j * stride`` of out
        k: [>= n] int64 in/out: samples so far per texel
    """
    dx = 1 if int(cp[CAM_WIDTH]) > 1 else 0
    dy = int(cp[CAM_REGION_WIDTH]) if int(cp[CAM_HEIGHT]) > 1 else 0
    tflat = tid.ravel()
    one = np.float32(1.0)
    for j in range(n):
        i00 = I00[j]
        if i00 < 0:
            continue
        if img[i00, 3] == 0:  # alpha: "all 4 bilinear taps in the eroded mask" (quad_foreground, region_rgba)
            continue
        if use_vis:
            ti = TI[j]
            if ti == -2:
                continue
            if ti >= 0:
                t = tflat[ti]
                own = own_tri[s0 + j]
                if t >= 0 and t != own and not _adjacent(faces, t, own):
                    den = planes[t, 0] * RAY[j, 1] + planes[t, 1] * RAY[j, 2] + planes[t, 2]
                    if den == 0:
                        continue  # ray parallel to the front triangle's plane (edge-on): occluded
                    zf = planes[t, 3] / den
                    if not (zf > 0) or RAY[j, 0] * (1.0 - eps / RAY[j, 3]) > zf:
                        continue
        fx = FX[j]
        fy = FY[j]
        gxf = one - fx
        gyf = one - fy
        row = row0 + j * stride + k[j]
        fin = True
        for q in range(3):
            if u8:  # x / 255 in float32 from a table: the same values without 12 divisions per sample
                a = _U8_TO_FLOAT[np.int64(img[i00, q])]
                b = _U8_TO_FLOAT[np.int64(img[i00 + dx, q])]
                c = _U8_TO_FLOAT[np.int64(img[i00 + dy, q])]
                e = _U8_TO_FLOAT[np.int64(img[i00 + dy + dx, q])]
            else:
                a = np.float32(img[i00, q])
                b = np.float32(img[i00 + dx, q])
                c = np.float32(img[i00 + dy, q])
                e = np.float32(img[i00 + dy + dx, q])
            v = (a * gxf + b * fx) * gyf + (c * gxf + e * fx) * fy
            out[row, q] = v
            if not math.isfinite(v):
                fin = False
        if fin:
            k[j] += 1


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, parallel=True)
def sample_view(P, Nrm, own_tri, faces, cp, img, u8, use_vis, tri_id, planes, eps, min_cos, rgb, ok):
    """Sample one view for every texel (see the module docstring; diagnostics and tests).

    Args:
        P, Nrm: [3, N] float64 texel points / unit normals (world)
        own_tri: [N] int32 each texel's triangle (of faces)
        faces: [F, 3] int mesh triangles (vertex ids)
        cp: [CAM_SIZE] float64 the packed camera (:func:`pack_camera`, :data:`CAMERA_ROW`)
        img: [w*h, 4] the :func:`region_rgba` buffer of cp's region: RGB float32 in [0, 1] or uint8, alpha the
            :func:`quad_foreground` flag
        u8: img is uint8 (read as ``x / 255``)
        use_vis: run the depth test against tri_id and planes
        tri_id: [Hc, Wc] int32 the crop of the grid at cp's crop origin (:func:`rasterize`)
        planes: [F, 4] float64 camera-space triangle planes (:func:`rasterize`)
        eps: depth-test tolerance along the ray (metres)
        min_cos: facing threshold on cos(normal, direction to the camera)
        rgb: [N, 3] float32 out: the sample (written only where seen)
        ok: [N] bool out: seen
    """
    N = P.shape[1]
    block = 1024
    Hc, Wc = tri_id.shape
    for b in numba.prange((N + block - 1) // block):
        s0 = b * block
        n = min(N, s0 + block) - s0
        I00 = np.empty(n, np.int64)
        TI = np.empty(n, np.int64)
        FX = np.empty(n, np.float32)
        FY = np.empty(n, np.float32)
        RAY = np.empty((n, 4))
        k = np.zeros(n, np.int64)
        _project_block(P, Nrm, s0, n, cp, min_cos, Hc, Wc, I00, FX, FY, RAY, TI)
        _sample_block(
            s0, n, own_tri, faces, cp, img, u8, use_vis, tri_id, planes, eps, I00, FX, FY, RAY, TI, rgb, s0, 1, k
        )
        for j in range(n):
            ok[s0 + j] = k[j] > 0


# --------------------------------------------------------------------------- fusion


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _fuse_one(s, row0, k, median_band, lo, hi, L, idx, keep, col, count, seen, i):
    """Fuse the k samples s[row0:row0+k] [k, 3] float32 (in view order) into col[i], count[i], seen[i]
    (scratch L float64, idx int64, keep bool, each of length >= k)."""
    seen[i] = min(k, 255) if seen.itemsize == 1 else k
    if k == 0:
        count[i] = 0
        col[i, 0] = 0.0
        col[i, 1] = 0.0
        col[i, 2] = 0.0
        return
    n_keep = 0
    if median_band:
        for m in range(k):
            L[m] = (
                0.2126 * np.float64(s[row0 + m, 0])
                + 0.7152 * np.float64(s[row0 + m, 1])
                + 0.0722 * np.float64(s[row0 + m, 2])
            )
        # stable order by luminance (ties keep view order) from each sample's rank, counted without branches:
        # the same order as an insertion sort, whose data-dependent branches cost ~7% of project_frame
        for m in range(k):
            lm = L[m]
            r = 0
            for q in range(k):  # one branch-free loop (vectorised): smaller, or equal and earlier
                r += (L[q] < lm) | ((L[q] == lm) & (q < m))
            idx[r] = m
        med = (L[idx[(k - 1) // 2]] + L[idx[k // 2]]) / 2
        for m in range(k):
            keep[m] = L[m] >= lo * med and L[m] <= hi * med
            n_keep += keep[m]
        if n_keep == 0:  # band kept nothing (even count, middle pair far apart): the two middle samples
            keep[idx[(k - 1) // 2]] = True
            keep[idx[k // 2]] = True
            n_keep = 1 if (k - 1) // 2 == k // 2 else 2
    else:
        for m in range(k):
            keep[m] = True
        n_keep = k
    t0 = 0.0
    t1 = 0.0
    t2 = 0.0
    for m in range(k):  # view order, float64
        if keep[m]:
            t0 += np.float64(s[row0 + m, 0])
            t1 += np.float64(s[row0 + m, 1])
            t2 += np.float64(s[row0 + m, 2])
    count[i] = min(n_keep, 255) if count.itemsize == 1 else n_keep
    col[i, 0] = np.float32(t0 / n_keep)
    col[i, 1] = np.float32(t1 / n_keep)
    col[i, 2] = np.float32(t2 / n_keep)


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, parallel=True)
def fuse(rgb, ok, median_band, lo, hi, col, count, seen):
    """Fuse per-texel view samples: rgb [C, N, 3] float32, ok [C, N] bool (rgb ignored where not ok)
    -> col [N, 3] float32 (0 where nothing kept), count [N], seen [N] int64 (written in place).

    Same rule and arithmetic as ``project_uv.fuse_samples``: Rec. 709 luminance in float64, median
    of the seen samples (mean of the two middle ones for an even count), keep ``lo*m <= L <= hi*m``;
    if nothing is kept, the two middle samples in a stable luminance order; mean of the kept RGB
    accumulated in float64 in view order.
    """
    C, N = ok.shape
    block = 4096
    for b in numba.prange((N + block - 1) // block):
        s = np.empty((C, 3), np.float32)
        L = np.empty(C)
        idx = np.empty(C, np.int64)
        keep = np.zeros(C, np.bool_)
        for i in range(b * block, min(N, (b + 1) * block)):
            k = 0
            for c in range(C):
                if ok[c, i]:
                    s[k, 0], s[k, 1], s[k, 2] = rgb[c, i, 0], rgb[c, i, 1], rgb[c, i, 2]
                    k += 1
            _fuse_one(s, 0, k, median_band, lo, hi, L, idx, keep, col, count, seen, i)


# --------------------------------------------------------------------------- whole frame

# A block of texels' bounds, as :func:`_block_bounds` writes them and :func:`_faces_away` reads them:
# a bounding sphere of the points and a cone of the normals.
_bnd = _RowLayout()
BND_CENTER_X = _bnd.field("CENTER_X", "bounding-sphere centre (mean of the block's points), world x (metres)")
BND_CENTER_Y = _bnd.field("CENTER_Y", "bounding-sphere centre, world y (metres)")
BND_CENTER_Z = _bnd.field("CENTER_Z", "bounding-sphere centre, world z (metres)")
BND_RADIUS = _bnd.field("RADIUS", "bounding-sphere radius (metres, widened by 1e-9 relative + 1e-12)")
BND_AXIS_X = _bnd.field("AXIS_X", "normal-cone axis (the normalised mean normal), x (unit vector)")
BND_AXIS_Y = _bnd.field("AXIS_Y", "normal-cone axis, y")
BND_AXIS_Z = _bnd.field("AXIS_Z", "normal-cone axis, z")
BND_HALF_ANGLE = _bnd.field(
    "HALF_ANGLE", "normal-cone half-angle (radians, + 1e-7); 4.0 (> pi: never culled) on a zero normal or no axis"
)
BND_SIZE = _bnd.size
"""Length of a block-bounds row (:func:`_block_bounds`)."""
BOUNDS_ROW: tuple[RowField, ...] = tuple(_bnd.fields)
"""The bounds row's fields in order; ``BND_<name>`` is each one's offset."""
del _bnd


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _block_bounds(P, Nrm, s0, n, out):
    """Bounds of a block's texels for :func:`_faces_away`: out [BND_SIZE] float64 (:data:`BOUNDS_ROW`: centre,
    radius, unit normal-cone axis, cone half-angle) of the points P[:, s0:s0+n] and unit normals
    Nrm[:, s0:s0+n] [3, N] float64; half-angle > pi when the block has a zero normal or no usable axis (never
    culled)."""
    cx = 0.0
    cy = 0.0
    cz = 0.0
    ax = 0.0
    ay = 0.0
    az = 0.0
    zero = False
    for j in range(n):
        i = s0 + j
        cx += P[0, i]
        cy += P[1, i]
        cz += P[2, i]
        ax += Nrm[0, i]
        ay += Nrm[1, i]
        az += Nrm[2, i]
        zero |= Nrm[0, i] * Nrm[0, i] + Nrm[1, i] * Nrm[1, i] + Nrm[2, i] * Nrm[2, i] < 0.25
    cx /= n
    cy /= n
    cz /= n
    la = math.sqrt(ax * ax + ay * ay + az * az)
    r2 = 0.0
    mindot = 1.0
    if la > 1e-9:
        ax /= la
        ay /= la
        az /= la
    for j in range(n):
        i = s0 + j
        dx, dy, dz = P[0, i] - cx, P[1, i] - cy, P[2, i] - cz
        r2 = max(r2, dx * dx + dy * dy + dz * dz)
        dn = Nrm[0, i] * ax + Nrm[1, i] * ay + Nrm[2, i] * az
        ln = math.sqrt(Nrm[0, i] * Nrm[0, i] + Nrm[1, i] * Nrm[1, i] + Nrm[2, i] * Nrm[2, i])
        mindot = min(mindot, dn / ln if ln > 0 else -1.0)
    out[BND_CENTER_X], out[BND_CENTER_Y], out[BND_CENTER_Z] = cx, cy, cz
    out[BND_RADIUS] = math.sqrt(r2) * (1 + 1e-9) + 1e-12
    out[BND_AXIS_X], out[BND_AXIS_Y], out[BND_AXIS_Z] = ax, ay, az
    out[BND_HALF_ANGLE] = 4.0 if zero or la <= 1e-9 else math.acos(max(-1.0, min(1.0, mindot))) + 1e-7


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, inline="always")
def _faces_away(bnd, cp, min_cos):
    """True when no texel of a block (bnd [BND_SIZE], :func:`_block_bounds`) can pass the facing test of the
    view whose packed camera is cp [CAM_SIZE] (its centre CAM_CENTER_X/Y/Z): every direction u from a texel to
    the camera lies within asin(r / L) of the direction from the block's centre (L its distance), every normal
    within the cone's half-angle of its axis, so the angle between normal and u is at least
    ``g = angle(axis, centre -> camera) - half-angle - asin(r / L)``; cull when ``cos(g) < min_cos`` (with a
    1e-7 margin on the angle and 1e-9 on the cosine)."""
    if bnd[BND_HALF_ANGLE] > 3.5:
        return False
    vx = cp[CAM_CENTER_X] - bnd[BND_CENTER_X]
    vy = cp[CAM_CENTER_Y] - bnd[BND_CENTER_Y]
    vz = cp[CAM_CENTER_Z] - bnd[BND_CENTER_Z]
    L = math.sqrt(vx * vx + vy * vy + vz * vz)
    r = bnd[BND_RADIUS]
    if not L > 2 * r:
        return False
    ca = (vx * bnd[BND_AXIS_X] + vy * bnd[BND_AXIS_Y] + vz * bnd[BND_AXIS_Z]) / L
    g = math.acos(max(-1.0, min(1.0, ca))) - bnd[BND_HALF_ANGLE] - math.asin(r / L) - 1e-7
    return g > 0 and math.cos(g) < min_cos - 1e-9


# not cached: it reads numba.get_num_threads() inside, a dynamic global numba cannot cache (it warns)
@numba.njit(cache=False, error_model="numpy", nogil=True, parallel=True)
def project_frame(
    P,
    Nrm,
    own_tri,
    faces,
    cams,
    imgs,
    u8,
    use_vis,
    tri_ids,
    planes,
    eps,
    min_cos,
    median_band,
    lo,
    hi,
    block,
    out_index,
    col,
    count,
    seen,
):
    """Sample every view and fuse, in blocks of ``block`` texels (a block's samples stay in cache).

    Texel i's result goes to row out_index[i] of col, count, seen; equal to :func:`fuse` of
    :func:`sample_view`'s samples (a texel's samples are appended in view order).

    Args:
        P, Nrm: [3, N] float64 texel points / unit normals (world)
        own_tri: [N] int32 each texel's triangle (of faces)
        faces: [F, 3] int mesh triangles (vertex ids)
        cams: [C, CAM_SIZE] float64 packed cameras (:func:`pack_camera`, :data:`CAMERA_ROW`)
        imgs: typed list of C [w*h, 4] uint8 or float32 :func:`region_rgba` buffers of each camera's region
        u8: the buffers are uint8 (read as ``x / 255``), else float32 in [0, 1]
        use_vis: run the depth test
        tri_ids: typed list of C [Hc, Wc] int32 triangle-id crops (:func:`rasterize`, at cp's crop origin)
        planes: typed list of C [F, 4] float64 camera-space triangle planes (:func:`rasterize`)
        eps: depth-test tolerance along the ray (metres)
        min_cos: facing threshold on cos(normal, direction to the camera)
        median_band: fuse by the median band (else the mean of all seen samples)
        lo, hi: the band ``lo * median <= L <= hi * median`` on luminance L
        block: texels per block
        out_index: [N] int the output row of each texel
        col: [M, 3] float32 out: fused colour (0 where nothing kept)
        count: [M] uint8 or int64 out: samples kept (uint8 saturates at 255)
        seen: [M] uint8 or int64 out: samples seen (uint8 saturates at 255)

    Per block: its bounds (:func:`_block_bounds`); per view, unless :func:`_faces_away` rejects the whole
    block, pass 1 (:func:`_project_block`, vectorised) and pass 2 (:func:`_sample_block`); then the fusion.
    Each thread takes every T-th block and keeps its scratch arrays (a 300 KB allocation per block was ~8 %
    of the kernel).
    """
    N = P.shape[1]
    C = cams.shape[0]
    nb = (N + block - 1) // block
    T = min(numba.get_num_threads(), max(nb, 1))
    for w in numba.prange(T):
        smp = np.empty((block * C, 3), np.float32)  # texel j's samples at rows j*C .. j*C + k[j]
        k = np.zeros(block, np.int64)
        I00 = np.empty(block, np.int64)
        TI = np.empty(block, np.int64)
        FX = np.empty(block, np.float32)
        FY = np.empty(block, np.float32)
        RAY = np.empty((block, 4))
        bnd = np.empty(BND_SIZE)
        L = np.empty(C)
        idx = np.empty(C, np.int64)
        keep = np.zeros(C, np.bool_)
        for b in range(w, nb, T):
            s0 = b * block
            n = min(N, s0 + block) - s0
            k[:n] = 0
            _block_bounds(P, Nrm, s0, n, bnd)
            for c in range(C):
                cp = cams[c]
                if _faces_away(bnd, cp, min_cos):
                    continue
                tid = tri_ids[c]
                Hc, Wc = tid.shape
                _project_block(P, Nrm, s0, n, cp, min_cos, Hc, Wc, I00, FX, FY, RAY, TI)
                _sample_block(
                    s0,
                    n,
                    own_tri,
                    faces,
                    cp,
                    imgs[c],
                    u8,
                    use_vis,
                    tid,
                    planes[c],
                    eps,
                    I00,
                    FX,
                    FY,
                    RAY,
                    TI,
                    smp,
                    0,
                    C,
                    k,
                )
            for j in range(n):
                _fuse_one(smp, j * C, k[j], median_band, lo, hi, L, idx, keep, col, count, seen, out_index[s0 + j])


# --------------------------------------------------------------------------- surface


@numba.njit(cache=CACHE, error_model="numpy", nogil=True, parallel=True)
def surface(vertices, normals, corners, bary, P, Nrm):
    """Texel points and unit normals by barycentric interpolation.

    vertices, normals [V, 3] float64; corners [N, 3] int (vertex ids), bary [N, 3] float64
    -> P, Nrm [3, N] float64 written in place (Nrm 0 where the interpolated normal vanishes).
    Same arithmetic as ``UVProjector._surface_soa``.
    """
    N = corners.shape[0]
    for i in numba.prange(N):
        c0, c1, c2 = corners[i, 0], corners[i, 1], corners[i, 2]
        b0, b1, b2 = bary[i, 0], bary[i, 1], bary[i, 2]
        for k in range(3):
            P[k, i] = b0 * vertices[c0, k] + b1 * vertices[c1, k] + b2 * vertices[c2, k]
            Nrm[k, i] = b0 * normals[c0, k] + b1 * normals[c1, k] + b2 * normals[c2, k]
        ln = math.sqrt(Nrm[0, i] * Nrm[0, i] + Nrm[1, i] * Nrm[1, i] + Nrm[2, i] * Nrm[2, i])
        s = 1.0 / ln if ln > 1e-12 else 0.0
        for k in range(3):
            Nrm[k, i] *= s
