"""A real, riggable human body for synthetic captures: the Anny body model (CC0 MakeHuman
mesh + the ``cmu_mb`` rig, whose bones match the CMU motion-capture BVH skeleton).

``build_anny_body(cache_dir)`` returns a :class:`Template` (rest mesh, per-corner UVs,
top-4 skin weights, face UV mask) and a :class:`Rig` (31 joints, Z-Y-X euler pose
parameters, 7 body-part groups) in gsavatar's conventions.

Coordinate conversion (Anny -> gsavatar template space)
------------------------------------------------------
Anny builds its data in a Blender-like frame: metres, **+Z up, the body faces -Y**, its
left side on +X. We map ``(x, y, z)_anny -> (x, z, -y)`` (a -90 degree rotation about X,
so the result is right-handed), giving **+Y up, facing +Z, left on +X**, the same axes as
the CMU BVH files. Then we translate so the feet touch ``y = 0`` (the lowest vertex) and
the pelvis (root joint ``Hips``) sits at ``x = z = 0``.

The first call with an empty ``cache_dir`` lets Anny build its model data (~70-80 s,
~0.7 GB under ``cache_dir``); the converted result is cached as
``cache_dir/gsavatar_body/<key>.npz`` + ``.rig.json`` so later calls take well under a
second and do not even import ``anny``.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from gsavatar.data_schema.rig import BODY_GROUPS, Joint, PoseParam, Rig, rig_from_json
from gsavatar.data_schema.template import SKIN_TOP_K, Template
from gsavatar.data_schema.template import topk_skin_weights as topk_weights  # moved down: importers use it too
from gsavatar.utils.io import atomic_save_npz

_CACHE_VERSION = 1
K_SKIN = SKIN_TOP_K
FACE_MASK_RES = 256

EULER_AXES: tuple[tuple[str, tuple[float, float, float]], ...] = (
    ("rz", (0.0, 0.0, 1.0)),
    ("ry", (0.0, 1.0, 0.0)),
    ("rx", (1.0, 0.0, 0.0)),
)
"""Pose parameters of every non-root joint, in listed (= multiplication) order: R = Rz Ry Rx."""

# Body-part group of each cmu_mb joint (the root "Hips" has no parameters).
JOINT_GROUPS: dict[str, str] = {
    "Hips": "torso_head",
    "LowerBack": "torso_head",
    "Spine": "torso_head",
    "Spine1": "torso_head",
    "Neck": "torso_head",
    "Neck1": "torso_head",
    "Head": "torso_head",
    "LHipJoint": "left_leg",
    "LeftUpLeg": "left_leg",
    "LeftLeg": "left_leg",
    "LeftFoot": "left_leg",
    "LeftToeBase": "left_leg",
    "RHipJoint": "right_leg",
    "RightUpLeg": "right_leg",
    "RightLeg": "right_leg",
    "RightFoot": "right_leg",
    "RightToeBase": "right_leg",
    "LeftShoulder": "left_arm",
    "LeftArm": "left_arm",
    "LeftForeArm": "left_arm",
    "RightShoulder": "right_arm",
    "RightArm": "right_arm",
    "RightForeArm": "right_arm",
    "LeftHand": "left_hand",
    "LeftFingerBase": "left_hand",
    "LeftHandFinger1": "left_hand",
    "LThumb": "left_hand",
    "RightHand": "right_hand",
    "RightFingerBase": "right_hand",
    "RightHandFinger1": "right_hand",
    "RThumb": "right_hand",
}

# Segmentation labels (anny/data/segmentation) added to the face mask besides the face
# skin: eyes and the mouth/eye cavities move with facial expression.
_FACE_EXTRA_LABELS = (
    "eye_front.L",
    "eye_front.R",
    "eye_back.L",
    "eye_back.R",
    "eye_cavity.L",
    "eye_cavity.R",
    "mouth_cavity",
)
_DROP_LABELS = ("tongue",)  # internal geometry, never visible in a closed-mouth capture


def anny_to_template_axes(p: np.ndarray) -> np.ndarray:
    """Anny (Z up, facing -Y) -> template axes (Y up, facing +Z): ``(x, y, z) -> (x, z, -y)``. [..., 3]"""
    p = np.asarray(p)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def group_of_joint(name: str) -> str:
    """Body-part group of a joint: the table above, else a name heuristic (for other rigs)."""
    if name in JOINT_GROUPS:
        return JOINT_GROUPS[name]
    n = name.lower()
    side = (
        "left"
        if (n.startswith("l") and not n.startswith("low")) or ".l" in n or "left" in n
        else ("right" if n.startswith("r") or ".r" in n or "right" in n else None)
    )
    if side is not None:
        if any(k in n for k in ("hand", "finger", "thumb", "wrist", "palm")):
            return f"{side}_hand"
        if any(k in n for k in ("shoulder", "clavicle", "arm", "elbow")):
            return f"{side}_arm"
        if any(k in n for k in ("hip", "leg", "knee", "foot", "toe", "ankle", "thigh", "shin")):
            return f"{side}_leg"
    return "torso_head"


def make_rig(names: list[str], parents: list[int], heads: np.ndarray) -> Rig:
    """Rig with three euler params (``.rz .ry .rx``) per non-root joint, grouped by body part."""
    joints = [
        Joint(n, None if p < 0 else names[p], tuple(float(x) for x in h))
        for n, p, h in zip(names, parents, np.asarray(heads))
    ]
    params: list[PoseParam] = []
    groups: dict[str, list[str]] = {g: [] for g in BODY_GROUPS}
    for j in joints:
        if j.parent is None:
            continue  # root: driven by root_rotation / root_translation
        for suffix, axis in EULER_AXES:
            p = PoseParam(f"{j.name}.{suffix}", j.name, "euler", axis)
            params.append(p)
            groups[group_of_joint(j.name)].append(p.name)
    rig = Rig(joints, params, groups)
    return rig_from_json(rig.to_json(), "anny_cmu_mb rig")  # validates (parents first, coverage)


# --------------------------------------------------------------------------------------
# public entry point
# --------------------------------------------------------------------------------------
def _cache_key(decimate_to: int | None, seed: int) -> str:
    dec = "full" if decimate_to is None else f"dec{int(decimate_to)}"
    return f"anny_cmu_mb_seed{int(seed)}_{dec}_v{_CACHE_VERSION}"


def build_anny_body(cache_dir: Path, decimate_to: int | None = None, seed: int = 0) -> tuple[Template, Rig]:
    """The Anny body (cmu_mb rig) as a gsavatar Template + Rig, cached under ``cache_dir``.

    cache_dir: Anny's model-data cache (``ANNY_CACHE_DIR``, ~0.7 GB once built) and ours.
    decimate_to: optional target vertex count (quadric decimation; UVs and skin weights
        transferred from the closest point of the full mesh) for fast tests.
    seed: 0 = Anny's default (average) phenotype; any other value draws a random adult
        phenotype (gender, age, muscle, weight, height) from ``numpy.random.default_rng(seed)``.
    """
    cache_dir = Path(cache_dir)
    if decimate_to is not None and int(decimate_to) < 100:
        raise ValueError(f"decimate_to must be >= 100 vertices, got {decimate_to}")
    ours = cache_dir / "gsavatar_body"
    key = _cache_key(decimate_to, seed)
    hit = _load_cached(ours, key)
    if hit is not None:
        return hit
    if decimate_to is None:
        tmpl, rig = _build_full(cache_dir, seed)
    else:
        full, rig = build_anny_body(cache_dir, None, seed)
        tmpl = decimate_template(full, int(decimate_to))
    _save_cached(ours, key, tmpl, rig)
    return tmpl, rig


def _load_cached(where: Path, key: str) -> tuple[Template, Rig] | None:
    npz, js = where / f"{key}.npz", where / f"{key}.rig.json"
    if not (npz.exists() and js.exists()):
        return None
    try:
        with np.load(npz) as z:
            t = Template(
                vertices=z["vertices"].astype(np.float32),
                faces=z["faces"].astype(np.int64),
                skin_indices=z["skin_indices"].astype(np.int32),
                skin_weights=z["skin_weights"].astype(np.float32),
                uvs=z["uvs"].astype(np.float32),
                face_uvs=z["face_uvs"].astype(np.int64),
                face_uv_mask=z["face_uv_mask"].astype(bool),
            )
        rig = rig_from_json(json.loads(js.read_text()), js)
    except (OSError, KeyError, ValueError, json.JSONDecodeError):
        return None  # corrupt/stale cache entry: rebuild
    return t, rig


def _save_cached(where: Path, key: str, t: Template, rig: Rig) -> None:
    atomic_save_npz(
        where / f"{key}.npz",
        vertices=t.vertices,
        faces=t.faces,
        skin_indices=t.skin_indices,
        skin_weights=t.skin_weights,
        uvs=t.uvs,
        face_uvs=t.face_uvs,
        face_uv_mask=t.face_uv_mask,
    )
    rig.save(where / f"{key}.rig.json")


# --------------------------------------------------------------------------------------
# building from anny
# --------------------------------------------------------------------------------------
def default_anny_cache() -> Path:
    """Anny's model-data cache when none is given: ``$ANNY_CACHE_DIR``, else ``~/.cache/gsavatar/anny``
    (read when called, never at import)."""
    env = os.environ.get("ANNY_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "gsavatar" / "anny"


def _import_anny(cache_dir: Path):
    cache_dir.mkdir(parents=True, exist_ok=True)
    try:
        import anny.paths
        from anny.face_segmentation import get_face_segmentation_mask
        from anny.models.phenotype import Anny
    except ImportError as e:
        raise ImportError(
            "build_anny_body needs the 'anny' body model package (CC0 MakeHuman body by NAVER LABS): "
            "install it with `pip install --no-deps anny` plus its small runtime deps "
            "`pip install roma trimesh requests` (see scripts/setup.sh), or pass an existing "
            f"template instead. Original error: {e}"
        ) from e
    # anny reads its cache path through get_anny_cache_path() when it builds model data, so setting it here
    # (rather than in this process's environment) is enough, whether or not anny was imported before.
    anny.paths.set_anny_cache_path(cache_dir)
    return Anny, get_face_segmentation_mask


def _phenotype(seed: int) -> dict[str, float]:
    if seed == 0:
        return {}
    rng = np.random.default_rng(seed)
    return {
        "gender": float(rng.uniform(0.0, 1.0)),
        "age": float(rng.uniform(0.55, 0.85)),  # anchors: child 1/3, young 2/3, old 1
        "muscle": float(rng.uniform(0.3, 0.7)),
        "weight": float(rng.uniform(0.3, 0.7)),
        "height": float(rng.uniform(0.3, 0.7)),
    }


def _build_full(cache_dir: Path, seed: int) -> tuple[Template, Rig]:
    import torch

    Anny, seg_mask = _import_anny(cache_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecations, "fallback to lbs skinning" (no NVIDIA warp)
        model = Anny(rig="cmu_mb", topology="anny", phenotype_blendshapes="original")
        with torch.no_grad():
            out = model(phenotype_kwargs=_phenotype(seed) or None)
    verts = anny_to_template_axes(out["rest_vertices"][0].double().cpu().numpy())  # [V, 3]
    heads = anny_to_template_axes(out["rest_bone_heads"][0].double().cpu().numpy())  # [J, 3]
    faces = model.faces.cpu().numpy().astype(np.int64)
    if faces.shape[1] != 3:
        raise RuntimeError(f"anny returned non-triangle faces {faces.shape}; expected the triangulated 'anny' topology")
    uvs = model.texture_coordinates.double().cpu().numpy()
    face_uvs = model.face_texture_coordinate_indices.cpu().numpy().astype(np.int64)
    names = list(model.bone_labels)
    parents = [int(p) for p in model.bone_parents]
    if any(p >= j for j, p in enumerate(parents)):
        raise RuntimeError("anny bones are not listed parents-first")
    w_dense = model.dense_vertex_bone_weights.double().cpu().numpy()  # [V, J]

    labels = {lab: seg_mask(model, [lab]).cpu().numpy() for lab in ("head",) + _FACE_EXTRA_LABELS + _DROP_LABELS}

    # --- frame: feet on y=0, pelvis at x=z=0 --------------------------------------
    shift = np.array([-heads[0, 0], -verts[:, 1].min(), -heads[0, 2]])
    verts = verts + shift
    heads = heads + shift

    # --- drop internal parts (tongue) and unreferenced vertices -------------------
    keep_f = ~np.any([labels[lab] for lab in _DROP_LABELS], axis=0)
    faces, face_uvs = faces[keep_f], face_uvs[keep_f]
    labels = {k: v[keep_f] for k, v in labels.items()}
    used = np.unique(faces)
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    verts, w_dense, faces = verts[used], w_dense[used], remap[faces]
    used_uv = np.unique(face_uvs)
    remap_uv = np.full(len(uvs), -1, np.int64)
    remap_uv[used_uv] = np.arange(len(used_uv))
    uvs, face_uvs = uvs[used_uv], remap_uv[face_uvs]

    idx, w = topk_weights(w_dense, K_SKIN)
    mask = face_uv_mask_from_mesh(verts, faces, uvs, face_uvs, labels, FACE_MASK_RES)
    tmpl = Template(
        vertices=verts.astype(np.float32),
        faces=faces,
        skin_indices=idx,
        skin_weights=w,
        uvs=uvs.astype(np.float32),
        face_uvs=face_uvs,
        face_uv_mask=mask,
    )
    return tmpl, make_rig(names, parents, heads)


# --------------------------------------------------------------------------------------
# face UV mask
# --------------------------------------------------------------------------------------
def rasterize_uv_faces(uvs: np.ndarray, face_uvs: np.ndarray, res: int) -> np.ndarray:
    """Pixels covered by the given UV triangles (v up; top row = v=1). -> [res, res] uint8 {0,255}"""
    import cv2

    img = np.zeros((res, res), np.uint8)
    tri = np.asarray(uvs, np.float64)[face_uvs]  # [F, 3, 2]
    px = np.stack([tri[..., 0] * res - 0.5, (1.0 - tri[..., 1]) * res - 0.5], -1)
    pts = np.round(px * 16).astype(np.int32)  # 4 fractional bits
    for t in pts:
        cv2.fillConvexPoly(img, t, 255, lineType=cv2.LINE_8, shift=4)
    return img


def face_uv_mask_from_mesh(
    verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray, face_uvs: np.ndarray, labels: dict[str, np.ndarray], res: int
) -> np.ndarray:
    """Face region (not scalp/ears/neck) in UV space. -> [res, res] bool, top row = v=1.

    Face skin = triangles of Anny's ``head`` segment that are in front of the ears, below
    the hairline and not under the jaw, measured from the eye centre in units of the
    eye-to-crown distance; the largest UV-connected piece of it is kept and small holes
    (nostrils, lip seams) closed. Eyes and mouth/eye cavities are added.
    """
    import cv2

    cen = verts[faces].mean(1)
    n = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    head = labels["head"]
    eyes = labels["eye_front.L"] | labels["eye_front.R"]
    if not head.any():
        raise RuntimeError("anny segmentation has no 'head' faces")
    top = cen[head, 1].max()
    eye = cen[eyes].mean(0) if eyes.any() else np.array([0.0, top - 0.11, cen[head, 2].max() - 0.03])
    s = top - eye[1]  # ~0.11 m for the average adult
    sel = head & (cen[:, 2] > eye[2] - 0.64 * s) & (cen[:, 1] < eye[1] + 0.5 * s) & (n[:, 1] > -0.5)
    skin = rasterize_uv_faces(uvs, face_uvs[sel], res)
    ncomp, comp, stats, _ = cv2.connectedComponentsWithStats(skin, connectivity=8)
    if ncomp > 1:
        big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        skin = np.where(comp == big, 255, 0).astype(np.uint8)
    k = max(3, (res // 64) | 1)
    skin = cv2.morphologyEx(skin, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    extra = np.any([labels[lab] for lab in _FACE_EXTRA_LABELS if lab in labels], axis=0)
    mask = (skin > 0) | (rasterize_uv_faces(uvs, face_uvs[extra], res) > 0)
    return mask


# --------------------------------------------------------------------------------------
# decimation
# --------------------------------------------------------------------------------------
def _closest_points(verts: np.ndarray, faces: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest surface point of ``query`` on the mesh: (triangle id [N], barycentrics [N, 3])."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(verts, np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)),
    )
    ans = scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(query, np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    pts = ans["points"].numpy().astype(np.float64)
    return tri, barycentric(verts[faces[tri]].astype(np.float64), pts, clamp=True)


def barycentric(tri: np.ndarray, p: np.ndarray, clamp: bool = False) -> np.ndarray:
    """Barycentrics of points projected onto their triangle's plane. tri [N,3,3], p [N,3] -> [N,3]"""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bc = np.stack([1.0 - v - w, v, w], 1)
    if clamp:
        bc = np.clip(bc, 0.0, None)
        bc /= np.clip(bc.sum(1, keepdims=True), 1e-12, None)
    return bc


def _uv_charts(face_uvs: np.ndarray, n_uv: int) -> np.ndarray:
    """UV chart id per triangle (triangles sharing a UV index are in one chart). -> [F]"""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    F = len(face_uvs)
    rows = np.repeat(np.arange(F), 3)
    g = sp.coo_matrix((np.ones(3 * F), (rows, F + face_uvs.ravel())), shape=(F + n_uv, F + n_uv))
    _, lab = connected_components(g, directed=False)
    return lab[:F]


def decimate_template(t: Template, target_vertices: int) -> Template:
    """Quadric-decimate ``t`` to about ``target_vertices`` vertices, transferring skin weights
    (barycentric, then top-K) and per-corner UVs from the closest point of the original mesh.

    Per-corner UVs: each new triangle takes the UV chart of the original triangle closest
    to its centroid; a corner whose own closest original triangle lies in that chart gets
    its interpolated UV, otherwise (the corner sits across a UV seam) the UV is
    extrapolated with the affine UV map of the centroid's triangle, so no triangle
    straddles two charts.
    """
    import open3d as o3d

    V0 = t.vertices.astype(np.float64)
    F0 = t.faces.astype(np.int64)
    if target_vertices >= len(V0):
        return t
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V0), o3d.utility.Vector3iVector(F0.astype(np.int32)))
    tri_target = int(2 * target_vertices)
    for _ in range(4):  # the vertex/triangle ratio is not exactly 1/2 (open parts): correct it
        m = mesh.simplify_quadric_decimation(target_number_of_triangles=tri_target)
        m.remove_degenerate_triangles()
        m.remove_unreferenced_vertices()
        nv = len(m.vertices)
        if abs(nv - target_vertices) <= 0.03 * target_vertices:
            break
        tri_target = max(4, int(round(tri_target * target_vertices / max(nv, 1))))
    V = np.asarray(m.vertices, np.float64)
    F = np.asarray(m.triangles, np.int64)

    # skin weights: barycentric blend of the dense weights of the closest original point
    J = int(t.skin_indices.max()) + 1
    W0 = np.zeros((len(V0), J))
    np.add.at(
        W0, (np.repeat(np.arange(len(V0)), t.skin_indices.shape[1]), t.skin_indices.ravel()), t.skin_weights.ravel()
    )
    tri_v, bc_v = _closest_points(V0, F0, V)
    W = np.einsum("nk,nkj->nj", bc_v, W0[F0[tri_v]])
    idx, w = topk_weights(W, t.skin_indices.shape[1])

    uvs = faces_uv = None
    if t.uvs is not None and t.face_uvs is not None:
        uv0 = t.uvs.astype(np.float64)
        fuv0 = t.face_uvs.astype(np.int64)
        chart = _uv_charts(fuv0, len(uv0))
        cen = V[F].mean(1)
        tri_c, _ = _closest_points(V0, F0, cen)  # chart of each new triangle
        tri_k = tri_v[F]  # [F, 3] closest original triangle of each corner
        # affine extrapolation of every corner with the centroid triangle's UV map
        ext = np.empty((len(F), 3, 2))
        own = np.empty((len(F), 3, 2))
        for k in range(3):
            p = V[F[:, k]]
            bc = barycentric(V0[F0[tri_c]], p, clamp=False)
            ext[:, k] = np.einsum("nk,nkd->nd", bc, uv0[fuv0[tri_c]])
            bc = barycentric(V0[F0[tri_k[:, k]]], p, clamp=True)
            own[:, k] = np.einsum("nk,nkd->nd", bc, uv0[fuv0[tri_k[:, k]]])
        # a corner keeps its own closest-point UV unless that lies in another chart or
        # jumps far from the extrapolation (a seam cut inside one chart)
        extent = np.linalg.norm(ext - np.roll(ext, 1, axis=1), axis=2).max(1, keepdims=True)  # [F, 1]
        same = chart[tri_k] == chart[tri_c][:, None]
        near = np.linalg.norm(own - ext, axis=2) < 0.5 * extent + 2e-3
        corner_uv = np.where((same & near)[..., None], own, ext)
        corner_uv = np.clip(corner_uv, 0.0, 1.0)
        uvs, faces_uv = np.unique(np.round(corner_uv.reshape(-1, 2), 7), axis=0, return_inverse=True)
        faces_uv = faces_uv.reshape(-1, 3).astype(np.int64)

    return Template(
        vertices=V.astype(np.float32),
        faces=F,
        skin_indices=idx,
        skin_weights=w,
        uvs=None if uvs is None else uvs.astype(np.float32),
        face_uvs=faces_uv,
        face_uv_mask=None if t.face_uv_mask is None else t.face_uv_mask.copy(),
    )


def body_summary(t: Template, rig: Rig) -> dict:
    """Counts for logs/docs."""
    return {
        "vertices": int(len(t.vertices)),
        "faces": int(len(t.faces)),
        "joints": rig.num_joints,
        "pose_dim": rig.pose_dim,
        "params_per_group": {g: len(rig.groups.get(g, [])) for g in BODY_GROUPS},
        "height_m": float(t.vertices[:, 1].max() - t.vertices[:, 1].min()),
        "face_mask_fraction": None if t.face_uv_mask is None else float(t.face_uv_mask.mean()),
    }


__all__ = [
    "build_anny_body",
    "decimate_template",
    "make_rig",
    "topk_weights",
    "anny_to_template_axes",
    "face_uv_mask_from_mesh",
    "body_summary",
]
