"""What an SMPL-X body loses in our LBS format, measured per body-part group over a sequence.

Our template is linear blend skinning of one rest mesh with top-K weights. SMPL-X adds, per frame, pose-corrective
blend shapes (``posedirs``, driven by ``R_j - I`` of joints 1-54) and expression blend shapes (which also move the
joints regressed from face vertices: jaw, eyes), and skins with dense weights. Each error below is the distance
between two SMPL-X surfaces that differ in one of these terms only, so it is exactly what leaving that term out
costs (the other terms off in both):

- :func:`posedirs_error`: with vs without pose correctives;
- :func:`expression_error`: with vs without expression;
- :func:`topk_error`: dense weights vs the template's top-K weights.

The surfaces come from :func:`smplx_surface_chunks`, a float64 SMPL-X forward pass (``smplx.lbs.lbs``'s maths,
written with ``geometry.rotations``; tests/importers compare it with the ``smplx`` package). A vertex belongs to
the group of its largest skinning weight's joint (the pelvis counts as ``torso_head``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from gsavatar.data_schema.rig import BODY_GROUPS
from gsavatar.data_schema.template import SKIN_TOP_K, topk_skin_weights
from gsavatar.geometry.rotations import axis_angle_to_matrix
from gsavatar.importers.smplx_body import shaped_vertices
from gsavatar.importers.smplx_model import SMPLX_JOINT_GROUPS, SMPLX_JOINT_NAMES, SmplxModel
from gsavatar.importers.smplx_params import SmplxParams, full_pose


class SurfaceError(NamedTuple):
    """Vertex distance between two surfaces per body-part group, millimetres."""

    mean_mm: dict[str, float]
    """Group -> mean over the sequence's frames and the group's vertices."""
    max_mm: dict[str, float]
    """Group -> largest over frames and vertices."""
    num_frames: int

    def table(self) -> str:
        """Markdown table, one row per group."""
        rows = ["| group | mean (mm) | max (mm) |", "|---|---|---|"]
        rows += [f"| {g} | {self.mean_mm[g]:.3f} | {self.max_mm[g]:.3f} |" for g in self.mean_mm]
        return "\n".join(rows)


def vertex_groups(model: SmplxModel) -> np.ndarray:
    """Group index (into BODY_GROUPS) of every vertex: its largest weight's joint's group.  # [V] int64"""
    of_joint = np.array([BODY_GROUPS.index(SMPLX_JOINT_GROUPS.get(n, "torso_head")) for n in SMPLX_JOINT_NAMES])
    return of_joint[np.argmax(model.weights, axis=1)]


def smplx_surface_chunks(
    model: SmplxModel,
    params: SmplxParams,
    *,
    posedirs: bool = True,
    expression: bool = True,
    weights: np.ndarray | None = None,
    flat_hand_mean: bool = True,
    chunk: int = 16,
):
    """SMPL-X posed vertices, frame chunk by frame chunk: yields (frame slice, vertices [B, V, 3] float64 metres).

    posedirs / expression: include the pose-corrective / expression blend shapes. weights: [V, 55] skinning
    weights (default: the model's). Expression coefficients past the model's columns are ignored (as a
    ``smplx.SMPLX`` built with ``num_expression_coeffs`` = the model's would need them cut).
    """
    f64 = dict(dtype=torch.float64)
    v0 = torch.as_tensor(shaped_vertices(model, params.betas), **f64)  # [V, 3]
    pose = torch.as_tensor(full_pose(params, model, flat_hand_mean), **f64)  # [F, 55, 3]
    W = torch.as_tensor(model.weights if weights is None else weights, **f64)  # [V, 55]
    Jreg = torch.as_tensor(model.J_regressor, **f64)  # [55, V]
    E = min(model.num_expression, params.expression.shape[1])
    exprdirs = torch.as_tensor(model.exprdirs[:, :, :E], **f64)  # [V, 3, E]
    expr = torch.as_tensor(params.expression[:, :E], **f64)  # [F, E]
    transl = torch.as_tensor(params.transl, **f64)  # [F, 3]
    V = v0.shape[0]
    pdirs = torch.as_tensor(model.posedirs.reshape(V * 3, -1), **f64) if posedirs else None  # [3V, 486]
    parents = model.parents.tolist()
    eye = torch.eye(3, **f64)
    for s in range(0, params.num_frames, chunk):
        sl = slice(s, min(s + chunk, params.num_frames))
        B = sl.stop - sl.start
        v = v0.expand(B, V, 3)
        if expression and E:
            v = v + torch.einsum("bk,vck->bvc", expr[sl], exprdirs)
        J = torch.einsum("jv,bvc->bjc", Jreg, v)  # [B, 55, 3] rest joints of this shape + expression
        R = axis_angle_to_matrix(pose[sl])  # [B, 55, 3, 3] local rotations, joint 0 = global_orient
        if pdirs is not None:
            v = v + ((R[:, 1:] - eye).reshape(B, -1) @ pdirs.T).reshape(B, V, 3)
        G, P = [None] * len(parents), [None] * len(parents)  # world rotation and posed head per joint
        for j, p in enumerate(parents):
            if p < 0:
                G[j], P[j] = R[:, j], J[:, j]  # the root turns about its own head J_0
            else:
                G[j] = G[p] @ R[:, j]
                P[j] = P[p] + (G[p] @ (J[:, j] - J[:, p])[..., None])[..., 0]
        Gs, Ps = torch.stack(G, 1), torch.stack(P, 1)
        t = Ps - (Gs @ J[..., None])[..., 0]  # posed_from_rest: x -> G x + t
        A = torch.cat([Gs, t[..., None]], -1)  # [B, 55, 3, 4]
        M = torch.einsum("vj,bjxy->bvxy", W, A)  # [B, V, 3, 4]
        yield sl, (M[..., :3] @ v[..., None])[..., 0] + M[..., 3] + transl[sl, None]


def _difference(model: SmplxModel, params: SmplxParams, a: dict, b: dict, flat_hand_mean: bool) -> SurfaceError:
    groups = torch.as_tensor(vertex_groups(model))
    G = len(BODY_GROUPS)
    total = torch.zeros(G, dtype=torch.float64)
    peak = torch.zeros(G, dtype=torch.float64)
    count = torch.bincount(groups, minlength=G).to(torch.float64)
    for (sl, va), (_, vb) in zip(
        smplx_surface_chunks(model, params, flat_hand_mean=flat_hand_mean, **a),
        smplx_surface_chunks(model, params, flat_hand_mean=flat_hand_mean, **b),
    ):
        d = torch.linalg.norm(va - vb, dim=-1) * 1000.0  # [B, V] mm
        total += torch.zeros(G, dtype=torch.float64).index_add_(0, groups, d.sum(0))
        peak = torch.maximum(
            peak, torch.zeros(G, dtype=torch.float64).scatter_reduce_(0, groups, d.max(0).values, reduce="amax")
        )
    F = params.num_frames
    mean = {g: float(total[i] / (count[i] * F)) if count[i] else 0.0 for i, g in enumerate(BODY_GROUPS)}
    return SurfaceError(mean, {g: float(peak[i]) for i, g in enumerate(BODY_GROUPS)}, F)


def posedirs_error(model: SmplxModel, params: SmplxParams, *, flat_hand_mean: bool = True) -> SurfaceError:
    """Distance between SMPL-X with and without pose correctives (no expression, dense weights, both)."""
    return _difference(
        model, params, dict(posedirs=True, expression=False), dict(posedirs=False, expression=False), flat_hand_mean
    )


def expression_error(model: SmplxModel, params: SmplxParams, *, flat_hand_mean: bool = True) -> SurfaceError:
    """Distance between SMPL-X with and without expression blend shapes (no pose correctives, dense weights)."""
    return _difference(
        model, params, dict(posedirs=False, expression=True), dict(posedirs=False, expression=False), flat_hand_mean
    )


def topk_error(
    model: SmplxModel, params: SmplxParams, *, top_k: int = SKIN_TOP_K, flat_hand_mean: bool = True
) -> SurfaceError:
    """Distance between SMPL-X skinned with its dense weights and with the template's top-K (no correctives)."""
    idx, w = topk_skin_weights(model.weights, top_k)
    dense = np.zeros_like(model.weights, dtype=np.float64)
    np.add.at(dense, (np.repeat(np.arange(len(idx)), idx.shape[1]), idx.ravel()), w.ravel())
    return _difference(
        model,
        params,
        dict(posedirs=False, expression=False),
        dict(posedirs=False, expression=False, weights=dense),
        flat_hand_mean,
    )
