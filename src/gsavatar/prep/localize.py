"""Per-anchor localization masks (paper section 3.2, "Localized Masking").

Pose mask ``m_i[j]`` (anchor ``i``, pose slot ``j``)
----------------------------------------------------
The paper sets ``m_i[j] = 1`` "iff any non-zero skinning weight affects θ[j]". Read
literally through forward kinematics, a parameter affects the transform of its own
joint and of *every descendant*, so root-near parameters (hips, spine) would be
active almost everywhere and the mask would not localize anything. We implement the
intent instead:

    slot j is active for anchor i iff the joint of slot j is a joint with non-zero
    skinning weight at the anchor, or one of that joint's ancestors up to
    ``ancestor_levels`` (default 1: the parent) levels up.

A bone's skinning region moves and deforms when its own joint rotates and, at the
joint boundary, when its parent rotates (the elbow region reacts to both shoulder
and elbow). ``ancestor_levels=0`` uses only the skinned joints themselves, a large
value gives the literal FK reading. Weights ``<= min_weight`` (default 0) count as
zero. All slots of one parameter (axis-angle triplets) share one column value.

Dilation (once): anchors are adjacent if either is among the other's ``k`` (default
6) Euclidean-nearest anchors (symmetric k-NN graph, no self loops); every anchor's
active entries are propagated to its adjacent anchors:
``m'_i = m_i OR (OR_{n ~ i} m_n)``. Alternatively :func:`geodesic_anchor_adjacency`
builds the adjacency from a geodesic Voronoi partition of the mesh (anchors whose
regions share a mesh edge), which never links anchors across a gap (e.g. inner
thighs, arm against torso); pass it as ``adjacency``.

Hands: finger parameters may cover no anchor, so every parameter of the
``left_hand`` / ``right_hand`` groups gets one shared column, the *wrist mask*:
the mask of the wrist joint ``W`` (as if ``W`` had a parameter; ``W`` = the lowest
common ancestor of the group's joints, e.g. ``LeftHand`` for the CMU rig, or given
explicitly) OR-ed with the masks of all the group's parameters, so a finger never
loses its own region. Computed before dilation (dilation distributes over OR, so
the order does not matter).

Face mask ``m^φ_i``: the anchor's UV falls in a True texel of the face UV mask
(nearest texel; the mask's top row is v = 1).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gsavatar.data_schema.localization import LocalizationMasks
from gsavatar.data_schema.rig import BODY_GROUPS, Rig

HAND_GROUPS = ("left_hand", "right_hand")


# --- joint / parameter relations -------------------------------------------------
def joint_activity(
    skin_indices: np.ndarray, skin_weights: np.ndarray, num_joints: int, min_weight: float = 0.0
) -> np.ndarray:
    """Joints with a skinning weight ``> min_weight`` per point.  # [N, J] bool"""
    N, K = skin_indices.shape
    act = np.zeros((N, num_joints), bool)
    rows = np.repeat(np.arange(N), K)
    keep = skin_weights.reshape(-1) > min_weight
    act[rows[keep], skin_indices.reshape(-1)[keep]] = True
    return act


def joint_reach(rig: Rig, ancestor_levels: int = 1) -> np.ndarray:
    """``R[s, q]``: a parameter on joint ``q`` is active where joint ``s`` is skinned,
    i.e. ``q == s`` or ``q`` is an ancestor of ``s`` at most ``ancestor_levels`` up.  # [J, J] bool
    """
    parents = rig.parents()
    J = len(parents)
    R = np.eye(J, dtype=bool)
    for s in range(J):
        q, lvl = parents[s], 0
        while q >= 0 and lvl < ancestor_levels:
            R[s, q] = True
            q, lvl = parents[q], lvl + 1
    return R


def lowest_common_ancestor(rig: Rig, joints: list[int]) -> int:
    parents = rig.parents()

    def chain(j: int) -> list[int]:
        out = [j]
        while parents[out[-1]] >= 0:
            out.append(int(parents[out[-1]]))
        return out[::-1]  # root first

    chains = [chain(j) for j in joints]
    lca = chains[0][0]
    for level in zip(*chains):
        if all(x == level[0] for x in level):
            lca = level[0]
        else:
            break
    return int(lca)


def wrist_joint_of_group(rig: Rig, group: str) -> int | None:
    """Joint index of the wrist of a hand group (LCA of its parameters' joints), None if empty."""
    names = set(rig.groups.get(group, []))
    joints = sorted({rig.joint_index(p.joint) for p in rig.params if p.name in names})
    return lowest_common_ancestor(rig, joints) if joints else None


# --- adjacency and dilation --------------------------------------------------------
def knn_anchor_adjacency(positions: np.ndarray, k: int = 6) -> np.ndarray:
    """Symmetric k-nearest-neighbour graph of the anchors (no self loops).  # [A, A] bool"""
    A = len(positions)
    k = min(k, A - 1)
    adj = np.zeros((A, A), bool)
    if k <= 0:
        return adj
    _, idx = cKDTree(np.asarray(positions, np.float64)).query(np.asarray(positions, np.float64), k=k + 1)
    for c in range(idx.shape[1]):
        adj[np.arange(A), idx[:, c]] = True
    np.fill_diagonal(adj, False)
    return adj | adj.T


def geodesic_anchor_adjacency(
    vertices: np.ndarray, faces: np.ndarray, face_idx: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Anchors whose geodesic Voronoi regions on the mesh share an edge.  # [A, A] bool

    Each anchor is snapped to the corner of its face with the largest barycentric;
    a multi-source Dijkstra over mesh edges assigns every vertex to its nearest
    anchor vertex; anchors are adjacent when a mesh edge joins their regions.
    Anchors snapped to the same vertex are adjacent to each other and share that
    region's adjacency.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    V = len(vertices)
    A = len(face_idx)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    length = np.linalg.norm(vertices[e[:, 0]].astype(np.float64) - vertices[e[:, 1]], axis=1)
    length = np.maximum(length, 1e-12)  # csgraph treats explicit zeros as missing edges
    g = coo_matrix((length, (e[:, 0], e[:, 1])), shape=(V, V)).tocsr()
    src_v = faces[face_idx, np.argmax(bary, axis=1)]
    uniq_v, first = np.unique(src_v, return_index=True)
    _, _, sources = dijkstra(g, directed=False, indices=uniq_v, min_only=True, return_predecessors=True)
    owner = np.full(V, -1, np.int64)  # vertex -> representative anchor
    vert_to_anchor = dict(zip(uniq_v.tolist(), first.tolist()))
    ok = sources >= 0
    owner[ok] = np.array([vert_to_anchor[s] for s in sources[ok].tolist()], dtype=np.int64)
    a, b = owner[e[:, 0]], owner[e[:, 1]]
    sel = (a >= 0) & (b >= 0) & (a != b)
    rep_adj = np.zeros((A, A), bool)
    rep_adj[a[sel], b[sel]] = True
    rep_adj |= rep_adj.T
    # expand representatives to all anchors snapped onto the same vertex
    rep = np.array([vert_to_anchor[v] for v in src_v.tolist()], dtype=np.int64)
    adj = rep_adj[rep][:, rep] | (rep[:, None] == rep[None, :])
    np.fill_diagonal(adj, False)
    return adj


def dilate_mask(mask: np.ndarray, adjacency: np.ndarray) -> np.ndarray:
    """One dilation step: ``m'_i = m_i OR any_{n adjacent to i} m_n``. [A, P] bool -> [A, P] bool"""
    adj = adjacency.astype(np.int32)
    return mask | ((adj @ mask.astype(np.int32)) > 0)


# --- masks -------------------------------------------------------------------------
def pose_masks(
    skin_indices: np.ndarray,
    skin_weights: np.ndarray,
    rig: Rig,
    positions: np.ndarray,
    dilate: bool = True,
    hand_uses_wrist: bool = True,
    ancestor_levels: int = 1,
    k_neighbors: int = 6,
    adjacency: np.ndarray | None = None,
    min_weight: float = 0.0,
    wrist_joints: dict[str, str] | None = None,
) -> np.ndarray:
    """Per-anchor binary pose masks (see module docstring).

    skin_indices/skin_weights: [A, K] of the anchors; positions: [A, 3] (for the k-NN
    adjacency; ignored when ``adjacency`` [A, A] bool is given) -> [A, P] bool.
    """
    A = len(skin_indices)
    act = joint_activity(np.asarray(skin_indices), np.asarray(skin_weights), rig.num_joints, min_weight)
    reach = joint_reach(rig, ancestor_levels)
    joint_mask = (act.astype(np.int32) @ reach.astype(np.int32)) > 0  # [A, J]: "a param on joint q is active"
    slot_joints = rig.slot_joints()
    mask = joint_mask[:, slot_joints]  # [A, P]
    if hand_uses_wrist:
        slot_groups = rig.slot_groups()
        for g in HAND_GROUPS:
            gi = BODY_GROUPS.index(g)
            slots = np.flatnonzero(slot_groups == gi)
            if len(slots) == 0:
                continue
            w = rig.joint_index(wrist_joints[g]) if wrist_joints and g in wrist_joints else wrist_joint_of_group(rig, g)
            col = joint_mask[:, w] | mask[:, slots].any(axis=1)
            mask[:, slots] = col[:, None]
    if dilate:
        if adjacency is None:
            adjacency = knn_anchor_adjacency(positions, k_neighbors)
        if adjacency.shape != (A, A):
            raise ValueError(f"adjacency must be [{A}, {A}], got {adjacency.shape}")
        mask = dilate_mask(mask, adjacency)
    return mask


def face_mask(uvs: np.ndarray, face_uv_mask: np.ndarray | None) -> np.ndarray:
    """Anchors whose UV lies in the face region (nearest texel; row 0 = v=1).  # [A] bool"""
    uvs = np.asarray(uvs, np.float64)
    if face_uv_mask is None:
        return np.zeros(len(uvs), bool)
    H, W = face_uv_mask.shape
    col = np.clip(np.floor(uvs[:, 0] * W), 0, W - 1).astype(np.int64)
    row = np.clip(np.floor((1.0 - uvs[:, 1]) * H), 0, H - 1).astype(np.int64)
    return np.asarray(face_uv_mask, bool)[row, col]


def active_per_point(anchor_active: np.ndarray, point_anchor_idx: np.ndarray) -> np.ndarray:
    """A point (Gaussian/control point) is active if any of its interpolation anchors is. [A], [N, k] -> [N] bool"""
    return np.asarray(anchor_active, bool)[point_anchor_idx].any(axis=1)


def build_localization(
    hierarchy,
    rig: Rig,
    face_uv_mask: np.ndarray | None,
    dilate: bool = True,
    hand_uses_wrist: bool = True,
    ancestor_levels: int = 1,
    k_neighbors: int = 6,
    adjacency: str = "knn",
    template=None,
    min_weight: float = 0.0,
) -> LocalizationMasks:
    """Pose and face masks for the anchors of a :class:`~gsavatar.data_schema.hierarchy.Hierarchy`.

    ``adjacency``: ``"knn"`` (default) or ``"geodesic"`` (needs ``template``).
    """
    a = hierarchy.anchors
    adj = None
    if dilate and adjacency == "geodesic":
        if template is None:
            raise ValueError("geodesic adjacency needs the template mesh")
        adj = geodesic_anchor_adjacency(template.vertices, template.faces, a.face_idx, a.bary)
    elif adjacency not in ("knn", "geodesic"):
        raise ValueError(f"adjacency must be 'knn' or 'geodesic', got {adjacency!r}")
    pose = pose_masks(
        a.skin_indices,
        a.skin_weights,
        rig,
        a.position,
        dilate=dilate,
        hand_uses_wrist=hand_uses_wrist,
        ancestor_levels=ancestor_levels,
        k_neighbors=k_neighbors,
        adjacency=adj,
        min_weight=min_weight,
    )
    face = face_mask(a.uv, face_uv_mask) if a.uv is not None else np.zeros(len(a), bool)
    settings = {
        "dilate": bool(dilate),
        "hand_uses_wrist": bool(hand_uses_wrist),
        "ancestor_levels": int(ancestor_levels),
        "adjacency": adjacency,
        "k_neighbors": int(k_neighbors),
        "min_weight": float(min_weight),
        "has_face_uv_mask": face_uv_mask is not None,
    }
    return LocalizationMasks(pose, face, [p.name for p in rig.params], settings)
