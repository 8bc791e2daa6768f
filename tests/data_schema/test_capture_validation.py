"""Capture validation: every kind of broken capture gives a SchemaError naming file and field."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema import SchemaError, check_images, load_capture
from minimal_capture import make_minimal_capture


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return make_minimal_capture(tmp_path_factory.mktemp("cap") / "capture")


@pytest.fixture
def cap(pristine, tmp_path) -> Path:
    dst = tmp_path / "capture"
    shutil.copytree(pristine, dst)
    return dst


def _edit_json(path: Path, fn) -> None:
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


def _edit_npz(path: Path, **changes) -> None:
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d.update(changes)
    for k in [k for k, v in d.items() if v is None]:
        del d[k]
    np.savez(path, **d)


def test_valid_capture_round_trips(cap):
    c = load_capture(cap)
    check_images(c)
    assert c.num_frames == 3 and set(c.cameras) == {"cam00", "cam01"}
    assert c.rig.pose_dim == 3 and c.motion.pose.shape == (3, 3)
    assert np.allclose(c.template.skin_weights.sum(1), 1)
    # round trip: rewrite metadata from the parsed objects and reload -> identical
    from gsavatar.data_schema import write_capture_metadata

    write_capture_metadata(cap, c.fps, c.num_frames, c.cameras, c.splits)
    c2 = load_capture(cap)
    for n in c.cameras:
        assert np.allclose(c.cameras[n].R, c2.cameras[n].R) and np.allclose(c.cameras[n].K, c2.cameras[n].K)
    assert c2.splits["train"].frames == c.splits["train"].frames


def _nan_pose(cap):
    with np.load(cap / "motion.npz") as z:
        p = z["pose"].copy()
    p[1, 2] = np.nan
    _edit_npz(cap / "motion.npz", pose=p)


def _bad_rotation(cap):
    _edit_json(cap / "calibration.json", lambda o: o["cam01"].__setitem__("R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]))


def _unnormalised_weights(cap):
    with np.load(cap / "template/skin_weights.npz") as z:
        w = z["weights"] * 1.5
    _edit_npz(cap / "template/skin_weights.npz", weights=w)


BROKEN = [
    # (name, mutate(cap), expected file suffix, expected substring of the message)
    ("missing capture.json", lambda c: (c / "capture.json").unlink(), "capture.json", "not found"),
    (
        "wrong format",
        lambda c: _edit_json(c / "capture.json", lambda o: o.update(format="x")),
        "capture.json",
        "format",
    ),
    (
        "future version",
        lambda c: _edit_json(c / "capture.json", lambda o: o.update(version=9)),
        "capture.json",
        "version",
    ),
    ("negative fps", lambda c: _edit_json(c / "capture.json", lambda o: o.update(fps=-3)), "capture.json", "fps"),
    (
        "K wrong shape",
        lambda c: _edit_json(c / "calibration.json", lambda o: o["cam00"].update(K=[[1, 0], [0, 1]])),
        "calibration.json",
        "cam00.K",
    ),
    ("R not a rotation", _bad_rotation, "calibration.json", "cam01.R"),
    (
        "T with NaN",
        lambda c: _edit_json(c / "calibration.json", lambda o: o["cam00"].update(T=[0, "NaN", 1])),
        "calibration.json",
        "cam00.T",
    ),
    (
        "imgSize missing",
        lambda c: _edit_json(c / "calibration.json", lambda o: o["cam00"].pop("imgSize")),
        "calibration.json",
        "cam00.imgSize",
    ),
    (
        "bad distortion",
        lambda c: _edit_json(c / "calibration.json", lambda o: o["cam00"].update(distCoeff=[0.1, 0.2])),
        "calibration.json",
        "distCoeff",
    ),
    ("NaN pose", _nan_pose, "motion.npz", "pose"),
    (
        "pose wrong width",
        lambda c: _edit_npz(c / "motion.npz", pose=np.zeros((3, 7), np.float32)),
        "motion.npz",
        "pose",
    ),
    (
        "root_translation missing",
        lambda c: _edit_npz(c / "motion.npz", root_translation=None),
        "motion.npz",
        "root_translation",
    ),
    (
        "too few frames in motion",
        lambda c: _edit_npz(c / "motion.npz", root_rotation=np.zeros((2, 3), np.float32)),
        "motion.npz",
        "root_rotation",
    ),
    ("unnormalised skin weights", _unnormalised_weights, "skin_weights.npz", "sum to 1"),
    (
        "skin index out of range",
        lambda c: _edit_npz(c / "template/skin_weights.npz", indices=np.full((8, 2), 5, np.int32)),
        "skin_weights.npz",
        "indices",
    ),
    (
        "unknown split camera",
        lambda c: _edit_json(c / "splits.json", lambda o: o["test"].update(cameras=["cam99"])),
        "splits.json",
        "cam99",
    ),
    (
        "split frame out of range",
        lambda c: _edit_json(c / "splits.json", lambda o: o["train"].update(frames=[0, 50])),
        "splits.json",
        "train.frames",
    ),
    (
        "empty split",
        lambda c: _edit_json(c / "splits.json", lambda o: o["test"].update(frames=[])),
        "splits.json",
        "test.frames",
    ),
    (
        "rig unknown parent",
        lambda c: _edit_json(c / "template/rig.json", lambda o: o["joints"][1].update(parent="Nope")),
        "rig.json",
        "parent",
    ),
    (
        "rig param in no group",
        lambda c: _edit_json(c / "template/rig.json", lambda o: o["groups"].update(torso_head=["Spine.rz"])),
        "rig.json",
        "groups",
    ),
    (
        "rig axis not unit",
        lambda c: _edit_json(c / "template/rig.json", lambda o: o["pose_params"][0].update(axis=[0, 0, 3])),
        "rig.json",
        "axis",
    ),
    (
        "truncated mesh.obj",
        lambda c: (c / "template/mesh.obj").write_text("v 0 0 0\nf 1 2 3\n"),
        "mesh.obj",
        "out of range",
    ),
    ("invalid JSON", lambda c: (c / "splits.json").write_text("{"), "splits.json", "invalid JSON"),
    ("missing image folder", lambda c: shutil.rmtree(c / "images" / "cam01"), "cam01", "not found"),
]


@pytest.mark.parametrize("name,mutate,file,needle", BROKEN, ids=[b[0] for b in BROKEN])
def test_broken_capture_names_file_and_field(cap, name, mutate, file, needle):
    mutate(cap)
    with pytest.raises(SchemaError) as ei:
        load_capture(cap)
    msg = str(ei.value)
    assert file in msg, msg
    assert needle in msg, msg


def test_missing_mask_and_wrong_image_size(cap):
    c = load_capture(cap)
    (cap / "masks" / "cam00" / "00000001.png").unlink()
    with pytest.raises(SchemaError, match=r"masks/cam00/00000001.png.*missing"):
        check_images(c)
    from gsavatar.utils.io import write_image

    write_image(cap / "masks" / "cam00" / "00000001.png", np.zeros((10, 10)))
    with pytest.raises(SchemaError, match=r"00000001.png: size: is 10x10"):
        check_images(c)


def test_truncated_image_is_reported(cap):
    from gsavatar.utils.io import read_image

    p = cap / "images" / "cam00" / "00000000.png"
    p.write_bytes(p.read_bytes()[:40])
    with pytest.raises(SchemaError, match="00000000.png"):
        read_image(p)
