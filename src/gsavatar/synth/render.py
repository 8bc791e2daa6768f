"""Ray-cast renderer for synthetic captures: posed textured mesh -> image + coverage mask.

- Geometry: the template posed by linear blend skinning (:func:`pose_vertices`), cast
  against with open3d's ``RaycastingScene`` (Embree). Rays go through pixel centres
  (or sub-pixel centres when supersampling) and honour OpenCV lens distortion
  (:func:`gsavatar.geometry.camera.pixel_rays`).
- Colour: the UV texture sampled bilinearly at the hit's interpolated per-corner UV
  (OBJ convention, v up: texel column ``x = u W - 0.5``, row ``y = (1 - v) H - 0.5``,
  clamped at the borders), times a mild Lambertian term
  ``ambient + diffuse * max(0, n . l)`` from one fixed world-space light.
- Mask: coverage of the body (0..1), the mean of the sub-pixel hits; occluders and
  the background are 0.

Ground truth vs. images: the per-frame texture the synthetic data saves as
``gt/textures`` is the UNSHADED albedo. The images are albedo x shading, so a UV
texture projected back from the images recovers albedo x shading, and the shading
term (ambient 0.65 + 0.35 diffuse by default, i.e. at most -35 %) is what bounds the
PSNR of a projected texture against the ground truth. Render with ``shading=None``
for images that are exactly the albedo (up to sampling and 8-bit quantisation).

open3d returns barycentrics ``primitive_uvs = (u, v)``: the weights of a triangle's
vertices 1 and 2; vertex 0 weighs ``1 - u - v``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from gsavatar.data_schema.capture import Camera
from gsavatar.data_schema.rig import Rig
from gsavatar.data_schema.template import Template
from gsavatar.geometry.camera import pixel_rays, project
from gsavatar.synth.appearance import vertex_normals


@dataclass(frozen=True)
class Shading:
    light_dir: tuple[float, float, float] = (0.35, 0.75, 0.55)
    """Direction TOWARD the light, world space (+Y up); normalised on use."""
    ambient: float = 0.65
    """Constant term of the shading factor."""
    diffuse: float = 0.35
    """Lambertian term weight; the factor spans [ambient, ambient + diffuse]."""


class TriMesh(NamedTuple):
    """An extra (untextured) object such as an occluder."""

    vertices: np.ndarray  # [V, 3] float32, world, metres
    faces: np.ndarray  # [F, 3] int64
    color: tuple[float, float, float]  # albedo, [0, 1]


class Hits(NamedTuple):
    """First ray hits (open3d/Embree)."""

    geometry: np.ndarray  # [N] int64: -1 miss, 0 the body, 1.. the extra objects in order
    primitive: np.ndarray  # [N] int64 triangle index within its geometry, -1 on a miss
    bary: np.ndarray  # [N, 3] float32 barycentric weights of the triangle's corners 0, 1, 2
    normal: np.ndarray  # [N, 3] float32 geometric (face) normal
    t: np.ndarray  # [N] float32 distance along the ray, inf on a miss


class RenderOutput(NamedTuple):
    image: np.ndarray  # [H, W, 3] float32 in [0, 1], RGB
    mask: np.ndarray  # [H, W] float32 body coverage in [0, 1]


def box_mesh(center: Sequence[float], size: Sequence[float], color=(0.5, 0.5, 0.5)) -> TriMesh:
    """Axis-aligned box. center [3], size [3] (full extents), metres."""
    c, s = np.asarray(center, np.float32), np.asarray(size, np.float32) / 2
    V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32) * s + c
    F = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        np.int64,
    )
    return TriMesh(V, F, tuple(map(float, color)))


def pose_vertices(
    template: Template,
    rig: Rig,
    pose: np.ndarray,
    root_rotation: np.ndarray,
    root_translation: np.ndarray,
    chunk: int = 16,
) -> np.ndarray:
    """Posed world vertices by LBS. pose [B, P] rad, root_rotation [B, 3] axis-angle,
    root_translation [B, 3] m -> [B, V, 3] float32."""
    import torch

    from gsavatar.geometry.lbs import RigTensors, lbs, skinning_transforms  # local like torch: lbs imports torch

    pose = np.asarray(pose, np.float32)
    if pose.ndim != 2 or pose.shape[1] != rig.pose_dim:
        raise ValueError(f"pose must be [B, {rig.pose_dim}], got {pose.shape}")
    rt = RigTensors(rig)
    pts = torch.as_tensor(template.vertices, dtype=torch.float32)
    idx = torch.as_tensor(template.skin_indices, dtype=torch.long)
    w = torch.as_tensor(template.skin_weights, dtype=torch.float32)
    out = []
    with torch.no_grad():
        for i in range(0, len(pose), chunk):
            T = skinning_transforms(
                rt,
                torch.as_tensor(pose[i : i + chunk]),
                torch.as_tensor(np.asarray(root_rotation[i : i + chunk], np.float32)),
                torch.as_tensor(np.asarray(root_translation[i : i + chunk], np.float32)),
            )
            out.append(lbs(pts, idx, w, T).numpy())
    return np.concatenate(out, 0).astype(np.float32)


def pose_joint_positions(
    rig: Rig, pose: np.ndarray, root_rotation: np.ndarray, root_translation: np.ndarray
) -> np.ndarray:
    """Posed world joint positions by forward kinematics (float64 inside). pose [F, P] rad, root_rotation [F, 3]
    axis-angle, root_translation [F, 3] m -> [F, J, 3] float64, metres."""
    import torch

    from gsavatar.geometry.lbs import pose_joints  # local like torch: geometry.lbs imports torch

    with torch.no_grad():
        return pose_joints(
            rig, *(torch.as_tensor(np.asarray(a), dtype=torch.float64) for a in (pose, root_rotation, root_translation))
        ).numpy()


def supersampled_rays(cam: Camera, supersample: int = 1) -> np.ndarray:
    """World rays (origin, unit dir) through the ``s x s`` sub-pixel centres of every pixel.

    Sub-pixel ``(X, Y)`` of the ``s``-times finer grid sits at pixel coordinate
    ``((X + 0.5) / s - 0.5, ...)``; that is a pinhole with ``K' = diag(s, s, 1) K`` and
    ``c' = s c + (s - 1) / 2``, and distortion acts on normalised coordinates, unchanged.
    -> [H*s, W*s, 6] float32
    """
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    K = cam.K.astype(np.float64).copy()
    K[:2] *= s
    K[:2, 2] += (s - 1) / 2.0
    return pixel_rays(K, cam.R, cam.T, cam.width * s, cam.height * s, cam.dist)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup, OBJ convention (v up), clamp-to-edge. texture [H, W, C], uv [N, 2] -> [N, C]."""
    H, W = texture.shape[:2]
    x = np.clip(uv[:, 0] * W - 0.5, 0.0, W - 1.0)
    y = np.clip((1.0 - uv[:, 1]) * H - 0.5, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2 if H > 1 else 0)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    t = texture
    top = t[y0, x0] * (1 - fx) + t[y0, x1] * fx
    bot = t[y1, x0] * (1 - fx) + t[y1, x1] * fx
    return top * (1 - fy) + bot * fy


class FrameScene:
    """One posed body (plus optional extra objects) ready for ray casting.

    vertices: posed world vertices [V, 3]; faces [F, 3]; corner_uvs [F, 3, 2] (OBJ v up).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        corner_uvs: np.ndarray,
        extras: Sequence[TriMesh] = (),
        nthreads: int = 0,
    ) -> None:
        import open3d as o3d

        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int64)
        self.corner_uvs = np.asarray(corner_uvs, np.float32)
        if self.corner_uvs.shape != (len(self.faces), 3, 2):
            raise ValueError(f"corner_uvs must be [F={len(self.faces)}, 3, 2], got {self.corner_uvs.shape}")
        self.normals = vertex_normals(self.vertices, self.faces)
        self.nthreads = nthreads
        self.extras = list(extras)
        self._scene = o3d.t.geometry.RaycastingScene(nthreads=nthreads)
        self._scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.faces.astype(np.uint32)))
        for m in self.extras:
            self._scene.add_triangles(
                o3d.core.Tensor(np.asarray(m.vertices, np.float32)), o3d.core.Tensor(np.asarray(m.faces, np.uint32))
            )

    def cast(self, rays: np.ndarray) -> Hits:
        """First hits of rays [N, 6] (origin, unit direction), world space."""
        import open3d as o3d

        ans = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, np.float32)), nthreads=self.nthreads)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        pid = ans["primitive_ids"].numpy().astype(np.int64)
        miss = gid == o3d.t.geometry.RaycastingScene.INVALID_ID
        gid[miss] = -1
        pid[miss] = -1
        w12 = ans["primitive_uvs"].numpy()
        bary = np.concatenate([1.0 - w12.sum(1, keepdims=True), w12], 1).astype(np.float32)
        return Hits(gid, pid, bary, ans["primitive_normals"].numpy(), ans["t_hit"].numpy())

    def shade(
        self, rays: np.ndarray, texture: np.ndarray, shading: Shading | None, background: Sequence[float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Colour and body coverage per ray. rays [N, 6] -> ([N, 3] float32, [N] float32)."""
        gid, pid, bary, gnorm, _ = self.cast(rays)
        n = len(rays)
        color = np.empty((n, 3), np.float32)
        color[:] = np.asarray(background, np.float32)
        body = gid == 0
        if body.any():
            f = pid[body]
            b = bary[body]
            uv = np.einsum("nk,nkc->nc", b, self.corner_uvs[f])
            albedo = sample_texture(texture, uv)
            if shading is not None:
                nrm = np.einsum("nk,nkc->nc", b, self.normals[self.faces[f]])
                albedo = albedo * _lambert(nrm, rays[body, 3:], shading)[:, None]
            color[body] = albedo
        for i, m in enumerate(self.extras, start=1):
            sel = gid == i
            if sel.any():
                c = np.broadcast_to(np.asarray(m.color, np.float32), (int(sel.sum()), 3))
                color[sel] = c * (_lambert(gnorm[sel], rays[sel, 3:], shading)[:, None] if shading else 1.0)
        return color, body.astype(np.float32)


def texel_visibility(
    scene: FrameScene, face_id: np.ndarray, bary: np.ndarray, cam: Camera, tol: float = 2e-3
) -> np.ndarray:
    """Which surface points (e.g. texel centres) a camera sees: in front of it, inside the
    image (with distortion) and the first hit of the ray from the camera centre.

    face_id [N] triangle index, bary [N, 3] barycentrics (on the posed body of ``scene``);
    tol: metres the first hit may lie in front of the point. -> [N] bool
    """
    p = np.einsum("nk,nkc->nc", bary.astype(np.float64), scene.vertices[scene.faces[face_id]].astype(np.float64))
    proj = project(p, cam.K, cam.R, cam.T, cam.dist)
    uv = proj.pixels
    ok = (
        (proj.depth > 1e-6)
        & (uv[:, 0] >= -0.5)
        & (uv[:, 0] < cam.width - 0.5)
        & (uv[:, 1] >= -0.5)
        & (uv[:, 1] < cam.height - 0.5)
    )
    c = cam.center
    d = p - c
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([np.broadcast_to(c, d.shape), d / np.maximum(dist, 1e-12)[:, None]], 1).astype(np.float32)
    hits = scene.cast(rays[ok])
    vis = np.zeros(len(p), bool)
    vis[ok] = (hits.geometry == 0) & (hits.t > dist[ok] - tol - 1e-3 * dist[ok])
    return vis


def _lambert(normals: np.ndarray, dirs: np.ndarray, shading: Shading) -> np.ndarray:
    """Shading factor per hit; normals are flipped to face the viewer (two-sided). -> [N]"""
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    flip = (n * dirs).sum(1) > 0
    n[flip] *= -1
    l = np.asarray(shading.light_dir, np.float32)
    l = l / np.linalg.norm(l)
    return (shading.ambient + shading.diffuse * np.maximum(n @ l, 0.0)).astype(np.float32)


def box_downsample(image: np.ndarray, s: int) -> np.ndarray:
    """Mean of every ``s x s`` block of a channels-last image. [H*s, W*s, C] -> [H, W, C]

    Bit-identical to ``image.reshape(H, s, W, s, C).mean((1, 3))`` (its test oracle): the block's samples are
    added in the order numpy's reduction adds them, row by row, then divided by ``s * s``. numpy reduces those
    two strided axes element by element (13-24 ms for one 512^2 x 3 float32 image on the 2-core box, against
    ~50 ms for shading the view); ``s * s`` whole-image additions take ~3 ms (benchmarks/bench_synth_render.py).
    """
    Hs, Ws, C = image.shape
    if s < 1 or Hs % s or Ws % s:
        raise ValueError(f"image of {Hs}x{Ws} does not split into {s}x{s} blocks")
    blocks = image.reshape(Hs // s, s, Ws // s, s, C)
    acc = blocks[:, 0, :, 0].copy()
    for i in range(s):
        for j in range(s):
            if i or j:
                acc += blocks[:, i, :, j]
    return acc / np.asarray(s * s, image.dtype)


def render_view(
    scene: FrameScene,
    cam: Camera,
    texture: np.ndarray,
    *,
    supersample: int = 2,
    shading: Shading | None = Shading(),
    background: Sequence[float] = (0.0, 0.0, 0.0),
    rays: np.ndarray | None = None,
) -> RenderOutput:
    """Render one camera. texture [S, S, 3] float in [0, 1]; rays: cached :func:`supersampled_rays`."""
    s = int(supersample)
    if rays is None:
        rays = supersampled_rays(cam, s)
    if rays.shape != (cam.height * s, cam.width * s, 6):
        raise ValueError(
            f"rays must be [{cam.height * s}, {cam.width * s}, 6] for camera {cam.name!r}, got {rays.shape}"
        )
    color, cov = scene.shade(rays.reshape(-1, 6), texture, shading, background)
    H, W = cam.height, cam.width
    img = box_downsample(color.reshape(H * s, W * s, 3), s)
    mask = cov.reshape(H, s, W, s).mean((1, 3))  # contiguous innermost axis: numpy's mean is fast here
    return RenderOutput(np.clip(img, 0, 1).astype(np.float32), mask.astype(np.float32))


def render_views(
    vertices: np.ndarray,
    faces: np.ndarray,
    corner_uvs: np.ndarray,
    texture: np.ndarray,
    cameras: Mapping[str, Camera],
    *,
    supersample: int = 2,
    shading: Shading | None = Shading(),
    background: Sequence[float] = (0.0, 0.0, 0.0),
    occluders: Mapping[str, Sequence[TriMesh]] | None = None,
    rays: Mapping[str, np.ndarray] | None = None,
    nthreads: int = 0,
) -> dict[str, RenderOutput]:
    """Render one posed frame in every camera.

    vertices [V, 3] posed world; faces [F, 3]; corner_uvs [F, 3, 2]; texture [S, S, 3].
    occluders: extra objects that exist only for the named camera (a view-specific occlusion).
    rays: per-camera cached :func:`supersampled_rays` (cameras are static over a capture).
    """
    occluders = occluders or {}
    scene = FrameScene(vertices, faces, corner_uvs, nthreads=nthreads)
    out = {}
    for name, cam in cameras.items():
        sc = scene
        if occluders.get(name):
            sc = FrameScene(vertices, faces, corner_uvs, extras=occluders[name], nthreads=nthreads)
        out[name] = render_view(
            sc,
            cam,
            texture,
            supersample=supersample,
            shading=shading,
            background=background,
            rays=None if rays is None else rays.get(name),
        )
    return out
