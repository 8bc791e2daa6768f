"""Ground-truth, time-varying appearance of the synthetic avatar, in UV space.

The synthetic captures reproduce the two problems the paper is about:

- **Pose--appearance ambiguity.** The garments switch between ``K`` discrete
  wrinkle/fold patterns (a Markov chain over frames, mean dwell ``fold_dwell_s``)
  and the hair/upper-back colours drift slowly. Both evolve with time, not with
  pose, so the same pose shows different appearances at different times.
- **Appearance caused by the motion's history** (``motion_effects``, on in the ``small`` preset):
  springs, hysteresis and accumulators driven by the posed joints
  (:mod:`gsavatar.synth.motion_effects`); the same pose looks different depending on how the body
  got there, and a predictor that sees the pose history can learn it.
- **Spurious correlation.** In *training* frames only, the trouser fold state is a
  function of one distant pose parameter (e.g. the right wrist rotation crossing a
  threshold). In test frames it follows its own pose-independent chain. A model
  that ties the trouser folds to the wrist memorises something that does not hold.

A small face embedding ``[F, E]`` (saved as ``motion.npz: face``) drives a mild
colour change of the face region, standing in for expressions.

Everything is deterministic from ``seed``. Per-texel surface attributes (rest
position, region masks, fold shading per state) are computed once; a frame's
texture is then a few vectorised array operations (:meth:`AppearanceModel.texture`).
Gutter texels (not covered by any UV triangle) copy the nearest covered texel so
bilinear lookups at chart borders do not bleed background into the renders.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from gsavatar.data_schema.rig import Rig
from gsavatar.data_schema.template import Template
from gsavatar.synth.motion_effects import MotionEffect, apply_effect, effect_level, hue_rotation, joint_signal


@dataclass(frozen=True)
class AppearanceConfig:
    num_fold_states: int = 4
    """Number K of discrete wrinkle/fold pattern states per garment (shirt, trousers)."""
    fold_dwell_s: float = 1.5
    """Mean time a fold state persists before switching (geometric dwell), seconds."""
    fold_strength: float = 0.32
    """Darkening at the bottom of a fold crease (0 = invisible, 1 = black)."""
    drift_period_s: float = 8.0
    """Time scale of the slow hair hue / upper-back patch drift, seconds."""
    hair_hue_range: float = 0.7
    """Largest hue rotation of the hair colour, radians about the grey axis."""
    back_patch_shift: float = 0.07
    """Largest vertical shift of the coloured patch on the upper back, metres."""
    face_dim: int = 4
    """Size E of the face embedding (``motion.npz: face [F, E]``)."""
    face_period_s: float = 2.0
    """Time scale of the face embedding, seconds."""
    face_strength: float = 0.15
    """Largest colour change the face embedding causes in the face region."""
    trouser_tint_range: float = 0.0
    """Largest hue rotation of the trousers (a slow, pose-independent re-dye drift), radians about the grey
    axis; 0 = off (the default; captures built before it existed stay byte-identical)."""
    trouser_tint_period_s: float = 3.0
    """Time scale of the trouser tint drift, seconds."""
    dye_garment: str = "none"
    """Garment whose colour switches between ``dye_states`` discrete dyes (a Markov chain over frames, mean
    dwell ``dye_dwell_s``, independent of pose): ``none``, ``shirt`` or ``trousers``. A large, pose-independent
    change that recurs, so held-out frames show states the training frames saw."""
    dye_states: int = 3
    """Number of dye states (state 0 = the garment's own colour)."""
    dye_dwell_s: float = 1.0
    """Mean time a dye state persists, seconds."""
    dye_strength: float = 0.45
    """Per-channel colour gains of the dyes are drawn from ``[1 - s, 1 + s]``."""
    coupling: bool = True
    """Tie the trouser fold state to the coupling pose signal in train frames (spurious correlation)."""
    coupling_hysteresis: float = 0.05
    """Half-width of the threshold's hysteresis band, in standard deviations of the signal."""
    motion_effects: tuple[MotionEffect, ...] = ()
    """Appearance mechanisms whose state is a causal function of the motion's history (springs, hysteresis,
    accumulators; :mod:`gsavatar.synth.motion_effects`). Need the posed joints (``joint_positions``)."""


class UVRaster(NamedTuple):
    """The template rasterised into its UV atlas (texel centres, OBJ convention, top row = v=1)."""

    face_id: np.ndarray  # [H, W] int64 triangle under the texel centre, -1 in gutters
    bary: np.ndarray  # [H, W, 3] float32 barycentric weights of that triangle's corners
    covered: np.ndarray  # [H, W] bool, a triangle covers the texel centre
    source: np.ndarray  # [H, W] int64 flat index of the covered texel a gutter texel copies (itself if covered)
    position: np.ndarray  # [H, W, 3] float32 rest-pose surface point, metres (gutters: nearest covered)
    normal: np.ndarray  # [H, W, 3] float32 rest-pose unit surface normal (gutters: nearest covered)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals. vertices [V, 3], faces [F, 3] -> [V, 3] float32."""
    v = np.asarray(vertices, dtype=np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def rasterize_uv(template: Template, size: int) -> UVRaster:
    """Find, for every texel centre of a ``size`` x ``size`` atlas, the triangle and barycentrics.

    Ray casts straight down onto the UV layout placed in the z=0 plane (open3d/Embree),
    which is exact and fast for any number of triangles.
    """
    import open3d as o3d
    from scipy import ndimage

    cuv = template.corner_uvs
    if cuv is None:
        raise ValueError("template has no UVs (uvs/face_uvs are None); the synthetic appearance lives in UV space")
    nf = cuv.shape[0]
    verts = np.concatenate([cuv.reshape(-1, 2), np.zeros((3 * nf, 1))], 1).astype(np.float32)
    tris = np.arange(3 * nf, dtype=np.uint32).reshape(nf, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    rays = np.zeros((size, size, 6), np.float32)
    rays[..., 0] = (xs + 0.5) / size
    rays[..., 1] = 1.0 - (ys + 0.5) / size
    rays[..., 2] = 1.0
    rays[..., 5] = -1.0
    ans = scene.cast_rays(o3d.core.Tensor(rays), nthreads=1)
    pid = ans["primitive_ids"].numpy().astype(np.int64)
    covered = pid != o3d.t.geometry.RaycastingScene.INVALID_ID
    if not covered.any():
        raise ValueError("no texel centre is covered by a UV triangle; are the UVs inside [0, 1]?")
    w12 = ans["primitive_uvs"].numpy().astype(np.float32)
    bary = np.concatenate([1.0 - w12.sum(-1, keepdims=True), w12], -1)
    face_id = np.where(covered, pid, -1)
    bary[~covered] = 0.0
    # Gutters copy the nearest covered texel (keeps bilinear lookups at chart borders clean).
    _, (iy, ix) = ndimage.distance_transform_edt(~covered, return_indices=True)
    source = (iy * size + ix).astype(np.int64)
    fid = face_id.ravel()[source.ravel()]
    b = bary.reshape(-1, 3)[source.ravel()]
    vid = template.faces[fid]  # [H*W, 3]
    pos = np.einsum("nk,nkc->nc", b, template.vertices[vid].astype(np.float32))
    vn = vertex_normals(template.vertices, template.faces)
    nrm = np.einsum("nk,nkc->nc", b, vn[vid])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return UVRaster(
        face_id,
        bary,
        covered,
        source,
        pos.reshape(size, size, 3).astype(np.float32),
        nrm.reshape(size, size, 3).astype(np.float32),
    )


# --------------------------------------------------------------------------- body regions
_KEYWORDS = {
    "head": ("head", "neck", "jaw", "eye", "tongue", "skull", "teeth", "face"),
    "hand": ("hand", "wrist", "finger", "thumb", "metacarpal", "index", "pinky", "carpal"),
    "forearm": ("forearm", "lowerarm"),
    "foot": ("foot", "toe", "ankle"),
}


def _joint_class(name: str) -> str | None:
    n = name.lower()
    for cls, words in _KEYWORDS.items():
        if any(w in n for w in words):
            return cls
    return None


def vertex_regions(template: Template, rig: Rig | None) -> dict[str, np.ndarray]:
    """Soft per-vertex body-part indicators from skin weights (joint-name keywords) and height.

    Returns ``{"head", "hand", "forearm", "foot": [V] float32 in [0, 1]}``; parts whose joints
    the rig does not name fall back to height bands of the rest pose (+Y up, feet at 0).
    """
    V = template.vertices
    height = float(V[:, 1].max() - V[:, 1].min())
    y = (V[:, 1] - V[:, 1].min()) / max(height, 1e-6)
    out: dict[str, np.ndarray] = {}
    classes = [_joint_class(j.name) for j in rig.joints] if rig is not None else []
    for cls in _KEYWORDS:
        sel = np.array([c == cls for c in classes], dtype=bool)
        if sel.any():
            w = (template.skin_weights * sel[template.skin_indices]).sum(1)
            out[cls] = np.clip(w, 0.0, 1.0).astype(np.float32)
        else:
            out[cls] = np.zeros(len(V), np.float32)
    if not out["head"].any():
        out["head"] = (y > 0.845).astype(np.float32)
    if not out["foot"].any():
        out["foot"] = (y < 0.045).astype(np.float32)
    return out


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _smooth_process(rng: np.random.Generator, n: int, fps: float, period_s: float, dims: int) -> np.ndarray:
    """Smooth random signals in [-1, 1]: sums of sinusoids with periods around ``period_s``. -> [n, dims]"""
    t = np.arange(n, dtype=np.float64)[:, None, None] / fps
    m = 4
    freq = rng.uniform(0.5, 1.6, (1, dims, m)) / period_s
    phase = rng.uniform(0, 2 * np.pi, (1, dims, m))
    amp = rng.uniform(0.5, 1.0, (1, dims, m))
    s = (amp * np.sin(2 * np.pi * freq * t + phase)).sum(-1) / amp.sum(-1)  # frame f does not depend on n
    return s.astype(np.float32)


def _markov_chain(rng: np.random.Generator, n: int, k: int, p_switch: float) -> np.ndarray:
    """States of a K-state chain that leaves its state with probability ``p_switch`` per frame. -> [n] int64"""
    s = np.empty(n, np.int64)
    cur = int(rng.integers(k))
    u = rng.random(n)
    jump = rng.integers(1, max(k, 2), n)
    for i in range(n):
        if i > 0 and k > 1 and u[i] < p_switch:
            cur = (cur + int(jump[i])) % k
        s[i] = cur
    return s


_SKIN = np.array([[0.87, 0.70, 0.58], [0.78, 0.58, 0.45], [0.62, 0.44, 0.32], [0.45, 0.31, 0.22], [0.93, 0.78, 0.68]])
_SHIRT = np.array([[0.20, 0.42, 0.70], [0.72, 0.22, 0.22], [0.25, 0.58, 0.35], [0.85, 0.72, 0.30], [0.55, 0.35, 0.65]])
_TROUSERS = np.array([[0.22, 0.25, 0.38], [0.45, 0.38, 0.28], [0.30, 0.30, 0.30], [0.55, 0.52, 0.45]])
_HAIR = np.array([[0.30, 0.20, 0.12], [0.55, 0.38, 0.18], [0.15, 0.12, 0.10], [0.60, 0.30, 0.15]])


class AppearanceModel:
    """Per-frame ground-truth UV albedo of the synthetic avatar.

    template: rest mesh with UVs (``corner_uvs``) and optionally ``face_uv_mask``.
    num_frames: F, length of the sequence.
    train_frames: frames in which the spurious coupling is active (default: none).
    coupling_signal: one pose parameter over the sequence, radians.  # [F]
        In train frames the trouser fold state is ``hi`` when it is above the train-frame
        median (with hysteresis), else ``lo``. None disables the coupling.
    rig: used only to find head/hand/forearm/foot vertices by joint name.
    joint_positions: posed world joint positions over the sequence, metres, +Y up.  # [F, J, 3]
        Needed when ``config.motion_effects`` is not empty; ``joint_names`` [J] names them.
    """

    def __init__(
        self,
        template: Template,
        num_frames: int,
        *,
        train_frames: Sequence[int] | None = None,
        coupling_signal: np.ndarray | None = None,
        rig: Rig | None = None,
        seed: int = 0,
        tex_size: int = 512,
        fps: float = 30.0,
        config: AppearanceConfig | None = None,
        joint_positions: np.ndarray | None = None,
        joint_names: Sequence[str] = (),
    ) -> None:
        if num_frames <= 0:
            raise ValueError(f"num_frames must be positive, got {num_frames}")
        if tex_size < 16:
            raise ValueError(f"tex_size must be >= 16, got {tex_size}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        cfg = config or AppearanceConfig()
        if cfg.num_fold_states < 1:
            raise ValueError(f"config.num_fold_states must be >= 1, got {cfg.num_fold_states}")
        self.config = cfg
        self.num_frames = int(num_frames)
        self.tex_size = int(tex_size)
        self.fps = float(fps)
        self.seed = int(seed)
        ss = np.random.SeedSequence(seed)
        r_col, r_fold, r_chain, r_drift, r_face, r_couple = (np.random.default_rng(s) for s in ss.spawn(6))
        self.uv = rasterize_uv(template, self.tex_size)
        self._build_regions(template, rig)
        self._build_base(r_col)
        self._build_folds(r_fold)
        self._build_dynamics(r_chain, r_drift, r_face, r_couple, train_frames, coupling_signal)
        # Its own stream (spawned past the first six), so turning it on changes nothing else.
        r_tint = np.random.default_rng(ss.spawn(1)[0])
        self.trouser_tint = (
            _smooth_process(r_tint, self.num_frames, self.fps, self.config.trouser_tint_period_s, 1)[:, 0]
            if self.config.trouser_tint_range > 0
            else np.zeros(self.num_frames)
        )
        cfg = self.config
        if cfg.dye_garment not in ("none", "shirt", "trousers"):
            raise ValueError(f"dye_garment must be 'none', 'shirt' or 'trousers', got {cfg.dye_garment!r}")
        self.dye = np.zeros(self.num_frames, np.int64)
        self._dye_gains = np.ones((1, 3), np.float32)
        if cfg.dye_garment != "none":
            if cfg.dye_states < 2 or not 0 < cfg.dye_strength < 1:
                raise ValueError(
                    f"dye_states must be >= 2 and dye_strength in (0, 1), got {cfg.dye_states}, {cfg.dye_strength}"
                )
            r_dye = np.random.default_rng(ss.spawn(1)[0])
            p = min(1.0, 1.0 / max(cfg.dye_dwell_s * self.fps, 1.0))
            self.dye = _markov_chain(r_dye, self.num_frames, cfg.dye_states, p)
            gains = r_dye.uniform(1 - cfg.dye_strength, 1 + cfg.dye_strength, (cfg.dye_states, 3)).astype(np.float32)
            gains[0] = 1.0
            self._dye_gains = gains
            self._dye_idx = np.flatnonzero(self.regions[cfg.dye_garment].ravel() > 1e-3)
            self._dye_w = self.regions[cfg.dye_garment].ravel()[self._dye_idx][:, None].astype(np.float32)
        self._trou_idx = np.flatnonzero(self.regions["trousers"].ravel() > 1e-3)
        self._trou_w = self.regions["trousers"].ravel()[self._trou_idx][:, None].astype(np.float32)
        self._build_motion_effects(joint_positions, joint_names)

    def _build_motion_effects(self, joint_positions: np.ndarray | None, joint_names: Sequence[str]) -> None:
        """Signals, states and texel sets of ``config.motion_effects`` (all frames, once)."""
        effects = tuple(self.config.motion_effects)
        self.motion_signals: dict[str, np.ndarray] = {}  # name -> [F]
        self.motion_levels: dict[str, np.ndarray] = {}  # name -> [F]
        self.motion_constants: dict[str, dict] = {}
        self._motion_texels: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        if not effects:
            return
        if joint_positions is None or np.shape(joint_positions)[:1] != (self.num_frames,):
            raise ValueError(
                f"config.motion_effects need joint_positions [num_frames={self.num_frames}, J, 3], got "
                f"{None if joint_positions is None else tuple(np.shape(joint_positions))}"
            )
        if len({e.name for e in effects}) != len(effects):
            raise ValueError(f"motion effect names must be unique, got {[e.name for e in effects]}")
        H = self.body_height
        y_all = ((self.uv.position[..., 1] - self._ymin()) / H).ravel()
        for e in effects:
            e.check()
            if e.region not in self.regions:
                raise ValueError(
                    f"motion effect {e.name!r}: region must be one of {sorted(self.regions)}, got {e.region!r}"
                )
            u = joint_signal(np.asarray(joint_positions), joint_names, e, self.fps)
            level, const = effect_level(e, u, self.fps)
            self.motion_signals[e.name], self.motion_levels[e.name], self.motion_constants[e.name] = u, level, const
            reach = abs(e.strength) / H + 0.5 * (e.y_range[1] - e.y_range[0]) if e.effect == "band" else 0.0
            lo, hi = e.y_range[0] - reach, e.y_range[1] + reach
            w = self.regions[e.region].ravel() * ((y_all >= lo) & (y_all <= hi))
            idx = np.flatnonzero(w > 1e-3)
            self._motion_texels.append((idx, w[idx][:, None].astype(np.float32), y_all[idx].astype(np.float32)))

    # ------------------------------------------------------------------ static maps
    def _build_regions(self, template: Template, rig: Rig | None) -> None:
        S = self.tex_size
        uv = self.uv
        src = uv.source.ravel()
        fid = uv.face_id.ravel()[src]
        b = uv.bary.reshape(-1, 3)[src]
        vid = template.faces[fid]
        vreg = vertex_regions(template, rig)
        reg = {k: np.einsum("nk,nk->n", b, v[vid]).reshape(S, S) for k, v in vreg.items()}
        p = uv.position
        ymin = float(template.vertices[:, 1].min())
        self.body_height = float(template.vertices[:, 1].max()) - ymin
        H = self.body_height
        y = (p[..., 1] - ymin) / H
        skin = np.maximum.reduce(
            [
                _smoothstep(0.35, 0.65, reg["head"]),
                _smoothstep(0.35, 0.65, reg["hand"]),
                _smoothstep(0.35, 0.65, reg["forearm"]),
            ]
        )
        shoe = _smoothstep(0.35, 0.65, reg["foot"]) * (1 - skin)
        trousers = (1 - _smoothstep(0.565, 0.575, y)) * (1 - skin) * (1 - shoe)
        shirt = np.clip(1 - skin - shoe - trousers, 0, 1)
        # Hair: top and back of the head region, away from the face mask.
        head = _smoothstep(0.35, 0.65, reg["head"])
        hp = p[head > 0.5]
        hc = hp.mean(0) if len(hp) else np.array([0.0, ymin + 0.93 * H, 0.0])
        face = np.zeros((S, S), np.float32)
        if template.face_uv_mask is not None:
            import cv2

            face = cv2.resize(template.face_uv_mask.astype(np.float32), (S, S), interpolation=cv2.INTER_LINEAR)
            face = face.ravel()[src].reshape(S, S)  # extend into gutters like every other map
        else:  # front of the head below the hairline
            face = head * _smoothstep(0.0, 0.3, uv.normal[..., 2]) * (1 - _smoothstep(0.955, 0.965, y))
        top = _smoothstep(0.945, 0.955, y)
        back = _smoothstep(0.02, -0.02, p[..., 2] - hc[2]) * _smoothstep(0.875, 0.885, y)
        hair = head * np.maximum(top, back) * (1 - _smoothstep(0.2, 0.5, face))
        self.regions = {"skin": skin, "shoe": shoe, "trousers": trousers, "shirt": shirt, "hair": hair, "face": face}
        self.regions = {k: v.astype(np.float32) for k, v in self.regions.items()}
        self._head_center = hc

    def _build_base(self, rng: np.random.Generator) -> None:
        S, H = self.tex_size, self.body_height
        p = self.uv.position.reshape(-1, 3).astype(np.float64)
        r = {k: v.reshape(-1, 1) for k, v in self.regions.items()}
        skin_c = _SKIN[rng.integers(len(_SKIN))]
        shirt_c = _SHIRT[rng.integers(len(_SHIRT))]
        trou_c = _TROUSERS[rng.integers(len(_TROUSERS))]
        self._hair_color = _HAIR[rng.integers(len(_HAIR))]
        shoe_c = np.array([0.12, 0.11, 0.10])
        # Subtle, position-based patterns (continuous across UV seams).
        stripe_period = rng.uniform(0.06, 0.09)
        stripes = 1 + 0.07 * _smoothstep(-0.3, 0.3, np.sin(2 * np.pi * p[:, 1] / stripe_period))[:, None]
        twill = 1 + 0.04 * np.sin(2 * np.pi * (p[:, 0] + p[:, 1] + 0.5 * p[:, 2]) / 0.035)[:, None]
        k = rng.normal(0, 1, (6, 3)) * (2 * np.pi / 0.35)
        ph = rng.uniform(0, 2 * np.pi, 6)
        lowfreq = 1 + 0.035 * np.sin(p @ k.T + ph).mean(1, keepdims=True)
        base = (
            r["skin"] * skin_c + r["shirt"] * shirt_c * stripes + r["trousers"] * trou_c * twill + r["shoe"] * shoe_c
        ) * lowfreq
        base = base * (1 - r["hair"]) + r["hair"] * self._hair_color * lowfreq
        # A contrasting chest logo on the shirt front (handy to eyeball registration).
        torso = self.regions["shirt"].reshape(-1) > 0.5
        front = torso & (self.uv.normal.reshape(-1, 3)[:, 2] > 0.5)
        if front.any():
            cand = p[front]
            target = np.array([0.0, self._ymin() + 0.72 * H, cand[:, 2].max()])
            c = cand[np.argmin(np.linalg.norm(cand - target, axis=1))]
            d = np.linalg.norm(p - c, axis=1)
            logo = (_smoothstep(0.055, 0.045, d) * (self.uv.normal.reshape(-1, 3)[:, 2] > 0.2))[:, None] * r["shirt"]
            base = base * (1 - logo) + logo * (1 - shirt_c) * 0.9
        self._base = np.clip(base, 0, 1).astype(np.float32).reshape(S, S, 3)
        # Upper-back patch (its position drifts over time): texels that can ever be inside it.
        back = torso & (self.uv.normal.reshape(-1, 3)[:, 2] < -0.3)
        self._patch_color = np.clip(hue_rotation(2.1) @ shirt_c * 1.25 + 0.1, 0, 1).astype(np.float32)
        if back.any():
            cand = p[back]
            target = np.array([0.0, self._ymin() + 0.70 * H, cand[:, 2].min()])
            self._patch_center = cand[np.argmin(np.linalg.norm(cand - target, axis=1))]
            reach = 0.08 + self.config.back_patch_shift + 0.01
            near = np.linalg.norm(p - self._patch_center, axis=1) < reach
            self._patch_idx = np.flatnonzero(near & (self.uv.normal.reshape(-1, 3)[:, 2] < 0.0))
        else:
            self._patch_center = np.zeros(3)
            self._patch_idx = np.zeros(0, np.int64)
        self._patch_pos = p[self._patch_idx].astype(np.float32)
        self._patch_w = r["shirt"][self._patch_idx].astype(np.float32)
        self._hair_idx = np.flatnonzero(self.regions["hair"].ravel() > 1e-3)
        self._hair_w = self.regions["hair"].ravel()[self._hair_idx][:, None]

    def _ymin(self) -> float:
        return float(self.uv.position[..., 1][self.uv.covered].min())

    def _build_folds(self, rng: np.random.Generator) -> None:
        """K crease patterns per garment: oriented ridge trains under Gaussian envelopes."""
        S, K = self.tex_size, self.config.num_fold_states
        p = self.uv.position.reshape(-1, 3).astype(np.float32)
        self._folds = {}
        for g in ("shirt", "trousers"):
            w = self.regions[g].ravel()
            cand = p[w > 0.5]
            maps = np.zeros((K, S * S), np.float32)
            if len(cand):
                for k in range(K):
                    acc = np.zeros(S * S, np.float32)
                    for _ in range(int(rng.integers(4, 8))):
                        c = cand[rng.integers(len(cand))]
                        d = rng.normal(0, 1, 3)
                        d[1] *= 2.5  # mostly horizontal creases (ridges run across the limb)
                        d /= np.linalg.norm(d)
                        lam = rng.uniform(0.03, 0.06)
                        sigma = rng.uniform(0.06, 0.12)
                        q = p - c
                        env = np.exp(-(q * q).sum(1) / (2 * sigma * sigma))
                        ridge = (0.5 + 0.5 * np.cos(2 * np.pi * (q @ d) / lam + rng.uniform(0, 2 * np.pi))) ** 3
                        acc = np.maximum(acc, (env * ridge).astype(np.float32))
                    maps[k] = acc * w
            self._folds[g] = maps.reshape(K, S, S)

    def _build_dynamics(self, r_chain, r_drift, r_face, r_couple, train_frames, coupling_signal) -> None:
        cfg, F = self.config, self.num_frames
        p_switch = min(1.0, 1.0 / max(cfg.fold_dwell_s * self.fps, 1.0))
        self.shirt_fold = _markov_chain(r_chain, F, cfg.num_fold_states, p_switch)
        self.trouser_fold_free = _markov_chain(r_chain, F, cfg.num_fold_states, p_switch)
        drift = _smooth_process(r_drift, F, self.fps, cfg.drift_period_s, 2)
        self.hair_drift, self.back_shift = drift[:, 0], drift[:, 1]
        self.face_embedding = _smooth_process(r_face, F, self.fps, cfg.face_period_s, cfg.face_dim)  # [F, E]
        self._face_tints = r_face.uniform(-1, 1, (cfg.face_dim, 3)).astype(np.float32)
        self._face_tints[:, 0] = np.abs(self._face_tints[:, 0])  # flush-like: mostly more red
        fm = self.regions["face"].ravel()
        self._face_idx = np.flatnonzero(fm > 1e-3)
        fp = self.uv.position.reshape(-1, 3)[self._face_idx]
        blobs = np.zeros((cfg.face_dim, len(self._face_idx)), np.float32)
        if len(fp):
            for j in range(cfg.face_dim):
                c = fp[r_face.integers(len(fp))]
                blobs[j] = np.exp(-((fp - c) ** 2).sum(1) / (2 * 0.03**2)) * fm[self._face_idx]
        self._face_blobs = blobs
        # Spurious coupling in train frames.
        self.train_frames = np.zeros(F, bool)
        if train_frames is not None:
            tf = np.asarray(list(train_frames), dtype=np.int64)
            if tf.size and (tf.min() < 0 or tf.max() >= F):
                raise ValueError(f"train_frames must lie in [0, {F}), got range [{tf.min()}, {tf.max()}]")
            self.train_frames[tf] = True
        self.trouser_fold = self.trouser_fold_free.copy()
        self.coupled = np.zeros(F, bool)
        self.coupling_threshold: float | None = None
        lo, hi = (int(x) for x in r_couple.choice(max(cfg.num_fold_states, 2), 2, replace=False))
        lo, hi = lo % cfg.num_fold_states, hi % cfg.num_fold_states
        self.coupling_states = (lo, hi)
        if cfg.coupling and coupling_signal is not None and self.train_frames.any():
            sig = np.asarray(coupling_signal, dtype=np.float64).reshape(-1)
            if sig.shape[0] != F:
                raise ValueError(f"coupling_signal must be [num_frames={F}], got {tuple(np.shape(coupling_signal))}")
            thr = float(np.median(sig[self.train_frames]))
            band = cfg.coupling_hysteresis * float(sig[self.train_frames].std())
            self.coupling_threshold = thr
            high = sig[0] > thr
            for f in range(F):
                if sig[f] > thr + band:
                    high = True
                elif sig[f] < thr - band:
                    high = False
                if self.train_frames[f]:
                    self.trouser_fold[f] = hi if high else lo
                    self.coupled[f] = True

    # ------------------------------------------------------------------ per frame
    def _check(self, frame: int) -> int:
        f = int(frame)
        if not 0 <= f < self.num_frames:
            raise ValueError(f"frame must be in [0, {self.num_frames}), got {frame}")
        return f

    def state(self, frame: int) -> dict:
        """The appearance state of ``frame`` (plain ints/floats/lists, JSON-ready)."""
        f = self._check(frame)
        out = {
            "frame": f,
            "shirt_fold": int(self.shirt_fold[f]),
            "trouser_fold": int(self.trouser_fold[f]),
            "trouser_fold_free": int(self.trouser_fold_free[f]),
            "hair_drift": float(self.hair_drift[f]),
            "back_shift": float(self.back_shift[f]),
            "face": [float(x) for x in self.face_embedding[f]],
            "coupled": bool(self.coupled[f]),
        }
        if self.config.trouser_tint_range > 0:  # only then: older captures keep their exact states
            out["trouser_tint"] = float(self.trouser_tint[f])
        if self.config.dye_garment != "none":
            out["dye"] = int(self.dye[f])
        if self.motion_levels:
            out["motion"] = {k: float(v[f]) for k, v in self.motion_levels.items()}
        return out

    def texture(self, frame: int) -> np.ndarray:
        """Unshaded UV albedo of ``frame``, OBJ convention (top row = v=1).  # [S, S, 3] float32 in [0, 1]"""
        f = self._check(frame)
        cfg = self.config
        shade = 1.0 - cfg.fold_strength * np.minimum(
            self._folds["shirt"][self.shirt_fold[f]] + self._folds["trousers"][self.trouser_fold[f]], 1.0
        )
        tex = self._base * shade[..., None]
        flat = tex.reshape(-1, 3)
        sflat = shade.reshape(-1)
        if len(self._hair_idx):
            M = hue_rotation(cfg.hair_hue_range * float(self.hair_drift[f]))
            h = flat[self._hair_idx]
            flat[self._hair_idx] = h + self._hair_w * (h @ M.T - h)
        if cfg.dye_garment != "none" and len(self._dye_idx):
            g = self._dye_gains[self.dye[f]]
            flat[self._dye_idx] *= 1 + self._dye_w * (g - 1)
        if self.config.trouser_tint_range > 0 and len(self._trou_idx):
            M = hue_rotation(cfg.trouser_tint_range * float(self.trouser_tint[f]))
            t = flat[self._trou_idx]
            flat[self._trou_idx] = t + self._trou_w * (t @ M.T - t)
        if len(self._patch_idx):
            c = self._patch_center + np.array([0.0, cfg.back_patch_shift * float(self.back_shift[f]), 0.0], np.float32)
            d = np.linalg.norm(self._patch_pos - c, axis=1)
            m = (_smoothstep(0.085, 0.075, d) * self._patch_w[:, 0])[:, None]
            flat[self._patch_idx] = (
                flat[self._patch_idx] * (1 - m) + m * self._patch_color * sflat[self._patch_idx, None]
            )
        if len(self._face_idx):
            delta = (self.face_embedding[f][:, None] * self._face_blobs).T @ self._face_tints  # [N, 3]
            flat[self._face_idx] += cfg.face_strength * delta
        for e, (idx, w, y) in zip(cfg.motion_effects, self._motion_texels):
            apply_effect(flat, idx, w, y, e, float(self.motion_levels[e.name][f]), self.body_height)
        return np.clip(tex, 0.0, 1.0).astype(np.float32, copy=False)

    def states(self) -> list[dict]:
        """:meth:`state` of every frame."""
        return [self.state(f) for f in range(self.num_frames)]
