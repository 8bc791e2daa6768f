"""An SMPL-X body as a capture's template, rig, skin weights and motion (capture format v1, docs/data_schema.md).

- Template: the shaped rest vertices ``v_template + shapedirs[..., :N] @ betas`` (no expression), the model's
  triangles, UVs when the model file (``vt``/``ft``) or a UV file gives them, the dense weights cut to the top
  :data:`~gsavatar.data_schema.template.SKIN_TOP_K` per vertex and renormalised.
- Rig: the 55 SMPL-X joints with rest heads ``J_regressor @ shaped vertices``, parents from ``kintree_table``; one
  ``axis_angle`` parameter (``<joint>.aa``, three slots) per non-root joint in SMPL-X joint order, grouped by
  :data:`~gsavatar.importers.smplx_model.GROUP_JOINTS`. SMPL-X's rest frames are world-aligned and a joint's
  rotation acts in its parent's frame, as in ``geometry.lbs``.
- Motion: ``pose`` = SMPL-X's full pose of joints 1-54 (``body_pose, jaw, leye, reye, left hand, right hand``,
  hand means added unless ``flat_hand_mean``), ``root_rotation = global_orient``, ``root_translation = transl``.
  Root convention: ours is ``world = R_root (x - head_root) + head_root + t_root``, SMPL-X's is
  ``R(global_orient) (x - J_0) + J_0 + transl`` with ``J_0`` the regressed pelvis, our root head: the same
  (tests/importers/test_smplx_body.py checks the posed surfaces against ``smplx`` itself).
- Face embedding (``motion.npz: face``): ``[expression, jaw_pose]`` per frame by default. Expression blend shapes
  and pose correctives are not geometry our LBS format stores; ``smplx_error`` measures what that costs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from gsavatar.data_schema.capture import Motion
from gsavatar.data_schema.rig import BODY_GROUPS, Joint, PoseParam, Rig, rig_from_json
from gsavatar.data_schema.template import SKIN_TOP_K, Template, save_template, topk_skin_weights, validate_template
from gsavatar.importers.smplx_model import SMPLX_JOINT_GROUPS, SMPLX_JOINT_NAMES, SmplxModel
from gsavatar.importers.smplx_params import SmplxParams, full_pose
from gsavatar.utils.errors import SchemaError

FaceEmbedding = Literal["expression_jaw", "expression", "none"]
"""What ``motion.npz: face`` holds: ``[expression, jaw_pose]`` (E + 3 columns), ``expression`` only, or nothing."""


class SmplxBody(NamedTuple):
    template: Template
    """Shaped rest mesh, skin weights, optional UVs."""
    rig: Rig
    """55 joints, 54 axis-angle parameters (pose dim 162), 7 groups."""


class ImportedBody(NamedTuple):
    template: Template
    rig: Rig
    motion: Motion


def param_name(joint: str) -> str:
    """Name of a joint's axis-angle parameter in rig.json."""
    return f"{joint}.aa"


def shaped_vertices(model: SmplxModel, betas: np.ndarray) -> np.ndarray:
    """``v_template + shapedirs[..., :N] @ betas``.  betas [N], N <= model.num_betas -> [V, 3] float64, metres."""
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)
    if len(betas) > model.num_betas:
        raise SchemaError(
            model.path,
            "shapedirs",
            f"the fit has {len(betas)} betas, the model {model.num_betas} shape "
            "columns (a 10-beta SMPL-X v1.0 model with a 300-beta fit?)",
        )
    return model.v_template.astype(np.float64) + model.shapedirs[:, :, : len(betas)].astype(np.float64) @ betas


def smplx_shape_basis(model: SmplxModel, num_betas: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Rest joints as a linear function of the first ``num_betas`` shape coefficients, for the body fit
    (``gsavatar.fitting.fit.ShapeBasis``): ``J_regressor v_template`` [55, 3] and ``J_regressor shapedirs[..., b]``
    per coefficient [B, 55, 3] (float64, metres)."""
    if not 0 < num_betas <= model.num_betas:
        raise ValueError(f"num_betas must be in [1, {model.num_betas}] for {model.path}, got {num_betas}")
    jr = model.J_regressor.astype(np.float64)
    heads = jr @ model.v_template.astype(np.float64)
    dheads = np.einsum("jv,vkb->bjk", jr, model.shapedirs[:, :, :num_betas].astype(np.float64))
    return heads, dheads


def smplx_rig(model: SmplxModel, heads: np.ndarray) -> Rig:
    """The SMPL-X rig with rest joint positions ``heads`` [55, 3] (metres)."""
    joints = [
        Joint(n, None if p < 0 else SMPLX_JOINT_NAMES[p], tuple(float(x) for x in h))
        for n, p, h in zip(SMPLX_JOINT_NAMES, model.parents.tolist(), np.asarray(heads))
    ]
    params = [PoseParam(param_name(j.name), j.name, "axis_angle") for j in joints[1:]]
    groups = {g: [param_name(n) for n in SMPLX_JOINT_NAMES[1:] if SMPLX_JOINT_GROUPS[n] == g] for g in BODY_GROUPS}
    rig = Rig(joints, params, groups)
    return rig_from_json(rig.to_json(), "smplx rig")  # the reader's checks: parents first, every param grouped


def smplx_template(
    model: SmplxModel, betas: np.ndarray, *, uvs: tuple[np.ndarray, np.ndarray] | None = None, top_k: int = SKIN_TOP_K
) -> SmplxBody:
    """The body of shape ``betas`` [N] as our template and rig.

    uvs: (uvs [T', 2], face_uvs [T, 3]) from :func:`~gsavatar.importers.smplx_model.load_smplx_uvs`; default: the
    model file's ``vt``/``ft`` if it has them, else none (prep's UV atlas stage makes them).
    """
    if top_k < 1:
        raise ValueError(f"top_k must be >= 1, got {top_k}")
    verts = shaped_vertices(model, betas)
    heads = model.J_regressor.astype(np.float64) @ verts  # [55, 3]
    if uvs is None and model.uvs is not None:
        uvs = (model.uvs, model.face_uvs)
    idx, w = topk_skin_weights(model.weights, top_k)
    t = Template(
        verts.astype(np.float32),
        model.faces.copy(),
        idx,
        w,
        None if uvs is None else uvs[0],
        None if uvs is None else uvs[1],
    )
    validate_template(t, len(SMPLX_JOINT_NAMES), Path("template"))
    return SmplxBody(t, smplx_rig(model, heads))


def smplx_motion(
    params: SmplxParams, model: SmplxModel, *, flat_hand_mean: bool = True, face: FaceEmbedding = "expression_jaw"
) -> Motion:
    """Our motion (pose in rig parameter order, root rotation/translation, face embedding) from a fit.

    flat_hand_mean: as the fit's ``smplx.SMPLX(flat_hand_mean=...)``; False adds the model's mean hand pose.
    """
    pose = full_pose(params, model, flat_hand_mean)  # [F, 55, 3]
    F = params.num_frames
    emb = {
        "expression_jaw": np.concatenate([params.expression, params.jaw_pose], axis=1),
        "expression": params.expression,
        "none": None,
    }
    if face not in emb:
        raise ValueError(f"face must be one of {sorted(emb)}, got {face!r}")
    e = emb[face]
    return Motion(
        pose=pose[:, 1:].reshape(F, -1).astype(np.float32),
        root_rotation=params.global_orient.astype(np.float32),
        root_translation=params.transl.astype(np.float32),
        face=None if e is None or e.shape[1] == 0 else e.astype(np.float32),
    )


def write_smplx_capture_body(
    out_dir: str | Path,
    model: SmplxModel,
    params: SmplxParams,
    *,
    uvs: tuple[np.ndarray, np.ndarray] | None = None,
    flat_hand_mean: bool = True,
    face: FaceEmbedding = "expression_jaw",
    top_k: int = SKIN_TOP_K,
) -> ImportedBody:
    """Write ``template/mesh.obj``, ``template/rig.json``, ``template/skin_weights.npz`` and ``motion.npz`` of a
    capture (atomic writes); capture.json, calibration, images and splits are the layout importer's."""
    out = Path(out_dir)
    body = smplx_template(model, params.betas, uvs=uvs, top_k=top_k)
    motion = smplx_motion(params, model, flat_hand_mean=flat_hand_mean, face=face)
    save_template(body.template, out / "template")
    body.rig.save(out / "template" / "rig.json")
    motion.save(out / "motion.npz")
    return ImportedBody(body.template, body.rig, motion)
