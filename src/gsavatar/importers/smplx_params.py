"""Per-frame SMPL-X parameters (a fit's ``smpl_params.npz``) and the full 55-joint pose they give.

Arrays (radians, axis-angle per joint, metres), F frames:

=====================  ==============  ==========================================================
key                    shape           default when absent
=====================  ==============  ==========================================================
``betas``              [N], [1, N]     required; one body shape (``[F, N]`` only if every row is equal)
``global_orient``      [F, 3]          required: pelvis rotation about the pelvis joint
``transl``             [F, 3]          required: added to every vertex after posing
``body_pose``          [F, 63]         required: joints 1-21
``jaw_pose``           [F, 3]          zeros
``leye_pose``          [F, 3]          zeros
``reye_pose``          [F, 3]          zeros
``left_hand_pose``     [F, 45]         zeros; [F, n < 45]: PCA coefficients (the model's ``hands_componentsl``)
``right_hand_pose``    [F, 45]         zeros; [F, n < 45]: PCA coefficients (``hands_componentsr``)
``expression``         [F, E]          zeros, E = 10
=====================  ==============  ==========================================================

``[F, k, 3]`` arrays are accepted as ``[F, 3k]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsavatar.data_schema.limits import check_motion_values
from gsavatar.importers.smplx_model import NUM_JOINTS, SmplxModel
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_npz

PER_FRAME: dict[str, int | None] = {
    "global_orient": 3,
    "transl": 3,
    "body_pose": 63,
    "jaw_pose": 3,
    "leye_pose": 3,
    "reye_pose": 3,
    "left_hand_pose": None,
    "right_hand_pose": None,
    "expression": None,
}
"""Per-frame arrays and their widths (None: checked elsewhere)."""
REQUIRED = ("betas", "global_orient", "transl", "body_pose")


@dataclass
class SmplxParams:
    """One SMPL-X fit over F frames (float64)."""

    betas: np.ndarray
    """Shape coefficients.  # [N]"""
    global_orient: np.ndarray
    """Pelvis rotation, axis-angle, about the pelvis joint.  # [F, 3]"""
    transl: np.ndarray
    """Translation added after posing, metres.  # [F, 3]"""
    body_pose: np.ndarray
    """Joints 1-21, axis-angle.  # [F, 63]"""
    jaw_pose: np.ndarray
    """# [F, 3]"""
    leye_pose: np.ndarray
    """# [F, 3]"""
    reye_pose: np.ndarray
    """# [F, 3]"""
    left_hand_pose: np.ndarray
    """15 finger joints, axis-angle, or n < 45 PCA coefficients.  # [F, 45] or [F, n]"""
    right_hand_pose: np.ndarray
    """# [F, 45] or [F, n]"""
    expression: np.ndarray
    """Expression coefficients.  # [F, E]"""

    @property
    def num_frames(self) -> int:
        return int(self.global_orient.shape[0])

    def frames(self, idx) -> SmplxParams:
        """The parameters of frames ``idx`` (an index array or slice)."""
        return SmplxParams(betas=self.betas, **{k: getattr(self, k)[idx] for k in PER_FRAME})

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], file: str | Path = "smpl_params.npz") -> SmplxParams:
        """Validate a fit's arrays (table above); SchemaError names ``file`` and the key."""
        file = Path(file)
        for k in REQUIRED:
            if k not in arrays:
                raise SchemaError(file, k, f"missing; has {sorted(arrays)}")
        out: dict[str, np.ndarray] = {}
        for k, a in arrays.items():
            if k not in PER_FRAME and k != "betas":
                continue
            a = np.asarray(a)
            if a.dtype.kind not in "biuf":
                raise SchemaError(file, k, f"expected real numbers, got dtype {a.dtype}")
            a = a.astype(np.float64)
            bad = ~np.isfinite(a)
            if bad.any():
                raise SchemaError(file, k, f"{int(bad.sum())} NaN/Inf values (first at {np.argwhere(bad)[0].tolist()})")
            if k in PER_FRAME and k != "expression":  # radians and metres (1e308 broke the rotation maths)
                check_motion_values(a, file, k)
            out[k] = a
        go = out["global_orient"]
        if go.ndim == 3 and go.shape[1:] == (1, 3):
            go = out["global_orient"] = go[:, 0]
        if go.ndim != 2 or go.shape[1] != 3 or go.shape[0] < 1:
            raise SchemaError(file, "global_orient", f"expected [F, 3] with F >= 1, got {list(go.shape)}")
        F = go.shape[0]
        for k, width in PER_FRAME.items():
            if k not in out:
                out[k] = np.zeros((F, 45 if k.endswith("hand_pose") else 10 if k == "expression" else width))
                continue
            a = out[k]
            if a.ndim == 3 and a.shape[2] == 3:
                a = out[k] = a.reshape(a.shape[0], -1)
            if a.ndim != 2 or a.shape[0] != F:
                raise SchemaError(
                    file, k, f"expected [{F}, {width or 'n'}] (F from global_orient), got {list(a.shape)}"
                )
            if width is not None and a.shape[1] != width:
                raise SchemaError(file, k, f"expected [{F}, {width}], got {list(a.shape)}")
            if k.endswith("hand_pose") and not 1 <= a.shape[1] <= 45:
                raise SchemaError(
                    file, k, f"expected [{F}, 45] axis-angle or [{F}, n <= 45] PCA coefficients, got {list(a.shape)}"
                )
        b = out["betas"]
        if b.ndim == 2 and len(b) >= 1:
            spread = float(np.abs(b - b[:1]).max())
            if spread > 1e-6:
                raise SchemaError(
                    file, "betas", f"vary across rows (by up to {spread:.3g}); a capture has one body shape"
                )
            b = b[0]
        if b.ndim != 1:
            raise SchemaError(file, "betas", f"expected [N] or [1, N], got {list(out['betas'].shape)}")
        out["betas"] = b
        return cls(**out)


def load_smplx_params(path: str | Path) -> SmplxParams:
    """Read a fit's npz (no pickles; the keys in the module doc) and validate it."""
    path = Path(path)
    return SmplxParams.from_arrays(read_npz(path, keys=("betas", *PER_FRAME)), path)


def hand_pose(coeffs: np.ndarray, side: int, model: SmplxModel, file: Path | str, key: str) -> np.ndarray:
    """[F, 45] axis-angle of one hand from [F, 45] axis-angle or [F, n] PCA coefficients (``side`` 0 = left)."""
    if coeffs.shape[1] == 45:
        return coeffs
    if model.hands_components is None:
        raise SchemaError(
            file,
            key,
            f"{coeffs.shape[1]} PCA coefficients, but {model.path.name} has no hands_componentsl/hands_componentsr",
        )
    comps = model.hands_components[side].astype(np.float64)
    if coeffs.shape[1] > len(comps):
        raise SchemaError(file, key, f"{coeffs.shape[1]} PCA coefficients, the model has {len(comps)} components")
    return coeffs @ comps[: coeffs.shape[1]]


def full_pose(
    params: SmplxParams, model: SmplxModel, flat_hand_mean: bool = True, file: Path | str = "smpl_params.npz"
) -> np.ndarray:
    """SMPL-X's full pose, one axis-angle per joint in :data:`SMPLX_JOINT_NAMES` order, as ``smplx.SMPLX(...,
    flat_hand_mean=flat_hand_mean)`` builds it (the model's ``hands_mean`` added when ``flat_hand_mean`` is False).

    -> [F, 55, 3] float64 radians; joint 0 is ``global_orient``.
    """
    F = params.num_frames
    hands = [
        hand_pose(getattr(params, f"{s}_hand_pose"), i, model, file, f"{s}_hand_pose")
        for i, s in enumerate(("left", "right"))
    ]
    if not flat_hand_mean:
        if model.hands_mean is None:
            raise SchemaError(model.path, "hands_meanl", "missing, and flat_hand_mean=False needs it")
        hands = [h + m.astype(np.float64) for h, m in zip(hands, model.hands_mean)]
    pose = np.concatenate(
        [params.global_orient, params.body_pose, params.jaw_pose, params.leye_pose, params.reye_pose, *hands], axis=1
    )
    return pose.reshape(F, NUM_JOINTS, 3)
