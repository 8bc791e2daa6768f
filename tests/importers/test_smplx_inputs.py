"""The SMPL-X model and fit readers refuse bad files naming the file and key, never unpickle, and the body's
options (UVs, face embedding, top-K) do what they say. Small fake models: no ``smplx`` package needed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema import BODY_GROUPS, SchemaError
from gsavatar.data_schema.template import load_template, topk_skin_weights
from gsavatar.geometry.mesh_io import write_obj
from gsavatar.importers import (
    SMPLX_JOINT_GROUPS,
    SMPLX_JOINT_NAMES,
    SmplxParams,
    load_smplx_model,
    load_smplx_params,
    load_smplx_uvs,
    smplx_motion,
    smplx_template,
    write_smplx_capture_body,
)
from gsavatar.importers.smplx_model import GROUP_JOINTS
from importers.fake_smplx import fake_smplx_arrays, random_fit

SMALL = dict(rings=3, segs=6)  # 990 vertices: enough for the readers (smplx itself needs >= 9930)


@pytest.fixture(scope="module")
def arrays() -> dict[str, np.ndarray]:
    return fake_smplx_arrays(**SMALL)


def save(tmp_path: Path, arrays: dict, **changes) -> Path:
    a = dict(arrays)
    for k, v in changes.items():
        if v is None:
            a.pop(k)
        else:
            a[k] = v
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(path, **a)
    return path


def test_every_joint_but_the_root_is_in_one_group():
    assert set(SMPLX_JOINT_GROUPS.values()) == set(BODY_GROUPS)
    assert set(SMPLX_JOINT_GROUPS) == set(SMPLX_JOINT_NAMES[1:])  # all 54, names spelled as in the joint list
    assert sum(len(js) for js in GROUP_JOINTS.values()) == 54  # none listed twice


def test_model_loads_without_unpickling(tmp_path, arrays):
    path = save(tmp_path, arrays)
    with np.load(path, allow_pickle=False) as z, pytest.raises(ValueError, match="pickle"):
        z["part2num"]  # the file holds a pickled member, like the official one ...
    m = load_smplx_model(path)  # ... which the reader never touches
    V = len(arrays["v_template"])
    assert m.num_vertices == V and m.num_betas == 10 and m.num_expression == 10
    assert m.parents[0] == -1 and m.faces.dtype == np.int64 and m.uvs is None
    np.testing.assert_array_equal(m.exprdirs, arrays["shapedirs"][:, :, 10:20])


def _bad_kintree(a):
    k = a["kintree_table"].copy()
    k[0, 5] = 4
    return k


def _rows(a):
    w = a["weights"].copy()
    w[3] *= 1.5
    return w


@pytest.mark.parametrize(
    ("key", "change", "message"),
    [
        ("posedirs", lambda a: None, "missing"),
        ("J_regressor", lambda a: a["J_regressor"][:54], r"expected shape \[55, "),
        ("J_regressor", lambda a: np.array(list(a["J_regressor"]), dtype=object), "pickled data is refused"),
        ("weights", _rows, "rows do not sum to 1"),
        ("weights", lambda a: -a["weights"], "negative"),
        ("kintree_table", _bad_kintree, "kinematic tree"),
        ("shapedirs", lambda a: np.where(np.arange(20) == 3, np.nan, a["shapedirs"]), "NaN"),
        ("shapedirs", lambda a: a["shapedirs"][:, :, :12], ">= 20"),
        ("posedirs", lambda a: a["posedirs"][:, :, :100], "486"),
        ("f", lambda a: a["f"] + np.uint32(len(a["v_template"])), "out of range"),
        ("v_template", lambda a: a["v_template"].astype(str), "real numbers"),
        ("ft", lambda a: np.zeros((3, 3), np.int64), "one UV index per corner"),
    ],
)
def test_bad_model_names_file_and_key(tmp_path, arrays, key, change, message):
    extra = {"vt": np.zeros((4, 2), np.float32)} if key == "ft" else {}
    path = save(tmp_path, arrays | extra, **{key: change(arrays)})
    with pytest.raises(SchemaError, match=message) as e:
        load_smplx_model(path)
    assert e.value.file == str(path) and e.value.field == key


def test_not_an_npz(tmp_path):
    p = tmp_path / "SMPLX_NEUTRAL.npz"
    p.write_bytes(b"\x80\x04pickle, not a zip")
    with pytest.raises(SchemaError, match="not an npz"):
        load_smplx_model(p)


# --------------------------------------------------------------------------------------------------- fits
def test_fit_defaults_and_shapes(tmp_path):
    fit = random_fit(4)
    fit["body_pose"] = fit["body_pose"].reshape(4, 21, 3)  # [F, 21, 3] is read as [F, 63]
    for k in ("jaw_pose", "leye_pose", "reye_pose", "left_hand_pose", "right_hand_pose", "expression"):
        del fit[k]
    np.savez(tmp_path / "smpl_params.npz", **fit)
    p = load_smplx_params(tmp_path / "smpl_params.npz")
    assert p.num_frames == 4 and p.betas.shape == (10,) and p.body_pose.shape == (4, 63)
    assert p.left_hand_pose.shape == (4, 45) and not p.left_hand_pose.any() and p.expression.shape == (4, 10)
    assert p.frames(slice(1, 3)).num_frames == 2


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("body_pose", None, "missing"),
        ("body_pose", np.zeros((4, 60)), r"expected \[4, 63\]"),
        ("transl", np.zeros((3, 3)), r"expected \[4, 3\]"),
        ("betas", np.arange(20.0).reshape(2, 10), "vary across rows"),
        ("global_orient", np.full((4, 3), np.nan), "NaN"),
        ("left_hand_pose", np.zeros((4, 46)), "PCA"),
        ("global_orient", np.zeros(3), r"expected \[F, 3\]"),
    ],
)
def test_bad_fit_names_file_and_key(tmp_path, key, value, message):
    fit = random_fit(4)
    if value is None:
        del fit[key]
    else:
        fit[key] = value
    np.savez(tmp_path / "smpl_params.npz", **fit)
    with pytest.raises(SchemaError, match=message) as e:
        load_smplx_params(tmp_path / "smpl_params.npz")
    assert e.value.field == key


def test_fit_and_model_must_agree(tmp_path, arrays):
    m = load_smplx_model(save(tmp_path, arrays, hands_componentsl=None, hands_componentsr=None))
    with pytest.raises(SchemaError, match="betas") as e:
        smplx_template(m, np.zeros(16))  # a 16-beta fit on a 10-column (v1.0) model
    assert e.value.field == "shapedirs"
    with pytest.raises(SchemaError, match="hands_componentsl") as e:
        smplx_motion(SmplxParams.from_arrays(random_fit(2, hand_cols=6)), m)  # PCA hands, no basis
    assert e.value.field == "left_hand_pose"


# --------------------------------------------------------------------------------------------------- options
def test_uvs_from_model_or_uv_file(tmp_path, arrays):
    with_uv = load_smplx_model(save(tmp_path, fake_smplx_arrays(uv=True, **SMALL)))
    out = tmp_path / "cap"
    body = write_smplx_capture_body(out, with_uv, SmplxParams.from_arrays(random_fit(2)))
    t = load_template(out / "template", 55)
    assert body.template.uvs is not None and t.uvs is not None and t.face_uvs.shape == t.faces.shape
    np.testing.assert_allclose(t.uvs, with_uv.uvs, atol=1e-6)

    plain = load_smplx_model(save(tmp_path, arrays))
    obj = tmp_path / "smplx_uv.obj"
    write_obj(obj, plain.v_template, plain.faces, with_uv.uvs, with_uv.face_uvs)
    uvs = load_smplx_uvs(obj, plain)
    assert smplx_template(plain, np.zeros(10), uvs=uvs).template.uvs is not None
    assert smplx_template(plain, np.zeros(10)).template.uvs is None  # no UVs anywhere: prep's atlas makes them
    write_obj(obj, plain.v_template, plain.faces[:, [0, 2, 1]], with_uv.uvs, with_uv.face_uvs)
    with pytest.raises(SchemaError, match="not the SMPL-X topology"):
        load_smplx_uvs(obj, plain)


def test_face_embedding_options(tmp_path, arrays):
    m = load_smplx_model(save(tmp_path, arrays))
    p = SmplxParams.from_arrays(random_fit(3, expression=True))
    assert smplx_motion(p, m).face.shape == (3, 13)
    np.testing.assert_allclose(smplx_motion(p, m, face="expression").face, p.expression.astype(np.float32))
    assert smplx_motion(p, m, face="none").face is None
    with pytest.raises(ValueError, match="face must be one of"):
        smplx_motion(p, m, face="jaw")


def test_hand_mean_is_added_unless_flat(tmp_path, arrays):
    m = load_smplx_model(save(tmp_path, arrays))
    p = SmplxParams.from_arrays(random_fit(2))
    flat, mean = smplx_motion(p, m).pose, smplx_motion(p, m, flat_hand_mean=False).pose
    np.testing.assert_allclose(mean[:, :72], flat[:, :72])  # body, jaw, eyes unchanged
    np.testing.assert_allclose(mean[:, 72:117] - flat[:, 72:117], np.broadcast_to(m.hands_mean[0], (2, 45)), atol=1e-6)


def test_topk_cut_keeps_largest_and_renormalises():
    w = np.zeros((2, 55))
    w[0, [3, 7, 9, 11, 20, 30]] = [0.4, 0.25, 0.15, 0.1, 0.06, 0.04]
    w[1, [5, 6]] = [0.7, 0.3]
    idx, ww = topk_skin_weights(w, 4)
    assert idx[0].tolist() == [3, 7, 9, 11] and np.allclose(ww[0], np.array([0.4, 0.25, 0.15, 0.1]) / 0.9)
    assert idx[1].tolist() == [5, 6, 5, 5] and np.allclose(ww[1], [0.7, 0.3, 0, 0])  # unused slots: main joint, 0
