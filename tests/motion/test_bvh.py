"""BVH reader: the shipped CMU file, arbitrary channel orders, FK, malformed files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsavatar.utils.errors import SchemaError
from gsavatar.motion.bvh import (
    bvh_global_transforms,
    bvh_joint_positions,
    bvh_local_transforms,
    bvh_rest_positions,
    read_bvh,
)

BVH_DIR = Path("/usr/share/assimp/models/BVH")
CMU_01_01 = BVH_DIR / "01_01.bvh"

CMU_JOINTS = [
    "Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
    "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LeftFingerBase", "LFingers", "LThumb",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RightFingerBase", "RFingers", "RThumb",
]  # fmt: skip


@pytest.fixture(scope="module")
def cmu():
    if not CMU_01_01.exists():
        pytest.skip(f"{CMU_01_01} not installed (apt package assimp-testmodels)")
    return read_bvh(CMU_01_01)


def test_parse_cmu_01_01(cmu):
    assert cmu.num_frames == 2752
    assert cmu.fps == pytest.approx(120.0, abs=1e-2)
    assert cmu.frame_time == pytest.approx(0.0083333)
    assert cmu.num_joints == 31
    assert cmu.names == CMU_JOINTS
    assert cmu.num_channels == 96 == cmu.motion.shape[1]
    assert cmu.channels[0] == ["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"]
    assert all(c == ["Zrotation", "Yrotation", "Xrotation"] for c in cmu.channels[1:])
    assert cmu.parents[0] == -1 and np.all(cmu.parents[1:] < np.arange(1, 31))
    assert cmu.parents[cmu.joint_index("LeftForeArm")] == cmu.joint_index("LeftArm")
    assert cmu.parents[cmu.joint_index("LThumb")] == cmu.joint_index("LeftHand")
    np.testing.assert_allclose(cmu.offsets[cmu.joint_index("LeftUpLeg")], [1.36306, -1.79463, 0.83929])
    assert len(cmu.end_sites) == 7  # toes x2, head, fingers x2, thumbs x2
    assert {cmu.names[j] for j, _ in cmu.end_sites} == {
        "LeftToeBase",
        "RightToeBase",
        "Head",
        "LFingers",
        "LThumb",
        "RFingers",
        "RThumb",
    }
    np.testing.assert_allclose(cmu.motion[0, :4], [9.3722, 17.8693, -17.3198, 0.0])
    assert np.all(np.isfinite(cmu.motion))
    np.testing.assert_array_equal(cmu.channel_start()[:3], [0, 6, 9])


def test_fk_consistency(cmu):
    frames = np.arange(0, cmu.num_frames, 97)
    G = bvh_global_transforms(cmu, frames)
    L = bvh_local_transforms(cmu, frames)
    assert G.shape == (len(frames), 31, 4, 4)
    # composition: G_j = G_parent L_j
    for j, p in enumerate(cmu.parents.tolist()):
        if p >= 0:
            np.testing.assert_allclose(G[:, j], G[:, p] @ L[:, j], atol=1e-9)
    # rotations are orthonormal, bone lengths = offset lengths in every frame
    R = G[..., :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    P = G[..., :3, 3]
    for j, p in enumerate(cmu.parents.tolist()):
        if p >= 0:
            np.testing.assert_allclose(
                np.linalg.norm(P[:, j] - P[:, p], axis=1), np.linalg.norm(cmu.offsets[j]), atol=1e-9
            )
    # root: translation channels + intrinsic Z-Y-X euler (degrees)
    m = cmu.motion[frames]
    np.testing.assert_allclose(P[:, 0], m[:, :3] + cmu.offsets[0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], Rotation.from_euler("ZYX", m[:, 3:6], degrees=True).as_matrix(), atol=1e-12)
    # a child joint: R = R_parent Rz Ry Rx
    j = cmu.joint_index("LeftForeArm")
    s = cmu.channel_start()[j]
    Rloc = Rotation.from_euler("ZYX", m[:, s : s + 3], degrees=True).as_matrix()
    np.testing.assert_allclose(R[:, j], R[:, cmu.parents[j]] @ Rloc, atol=1e-9)
    # frames=None/int/slice agree; rest pose = cumulative offsets
    np.testing.assert_allclose(bvh_joint_positions(cmu, 97)[0], P[1])
    np.testing.assert_allclose(bvh_global_transforms(cmu, slice(0, 98, 97)), G[:2])
    zero = cmu.__class__(**{**cmu.__dict__, "motion": np.zeros((1, cmu.num_channels))})
    np.testing.assert_allclose(bvh_joint_positions(zero)[0], bvh_rest_positions(cmu), atol=1e-12)


SMALL = """HIERARCHY
ROOT root
{
  OFFSET 1 2 3
  CHANNELS 4 Yrotation Xposition Zposition Xrotation
  JOINT mid
  {
    OFFSET 0 1 0
    CHANNELS 4 Xrotation Yposition Zrotation Yrotation
    End Site
    {
      OFFSET 0 0 1
    }
  }
  JOINT still
  {
    OFFSET 1 0 0
    CHANNELS 0
  }
}
MOTION
Frames: 2
Frame Time: 0.04
0 0 0 0   0 0 0 0
90 0.5 -1 30   45 2 10 -20
"""


def _write(tmp_path: Path, text: str, name: str = "x.bvh") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_arbitrary_channel_orders_and_positions(tmp_path):
    b = read_bvh(_write(tmp_path, SMALL))
    assert b.names == ["root", "mid", "still"]
    assert b.channels == [
        ["Yrotation", "Xposition", "Zposition", "Xrotation"],
        ["Xrotation", "Yposition", "Zrotation", "Yrotation"],
        [],
    ]
    assert b.num_channels == 8 and b.fps == pytest.approx(25.0)
    assert len(b.end_sites) == 1 and b.end_sites[0][0] == 1
    G = bvh_global_transforms(b)
    np.testing.assert_allclose(G[0, :, :3, 3], [[1, 2, 3], [1, 3, 3], [2, 2, 3]], atol=1e-12)
    # frame 1 by hand: local = T(offset + pos) @ R(listed order)
    r = lambda ax, d: Rotation.from_euler(ax, d, degrees=True).as_matrix()  # noqa: E731
    R0 = r("y", 90) @ r("x", 30)
    t0 = np.array([1 + 0.5, 2, 3 - 1])
    R1 = r("x", 45) @ r("z", 10) @ r("y", -20)
    t1 = np.array([0, 1 + 2, 0])
    np.testing.assert_allclose(G[1, 0, :3, :3], R0, atol=1e-12)
    np.testing.assert_allclose(G[1, 0, :3, 3], t0, atol=1e-12)
    np.testing.assert_allclose(G[1, 1, :3, :3], R0 @ R1, atol=1e-12)
    np.testing.assert_allclose(G[1, 1, :3, 3], t0 + R0 @ t1, atol=1e-12)
    np.testing.assert_allclose(G[1, 2, :3, 3], t0 + R0 @ np.array([1.0, 0, 0]), atol=1e-12)


def _broken(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


@pytest.mark.parametrize(
    "mutate, line, words",
    [
        (lambda s: s.split("MOTION")[0], None, "no MOTION"),
        (lambda s: s.rsplit("90 0.5", 1)[0], 24, "truncated"),  # only 1 of 2 frame rows
        (lambda s: _broken(s, "90 0.5 -1 30   45 2 10 -20", "90 0.5 -1 30   45 2 10"), 25, "has 7 values"),
        (lambda s: _broken(s, "90 0.5 -1 30   45 2 10 -20", "90 0.5 -1 nan   45 2 10 -20"), 25, "NaN"),
        (lambda s: _broken(s, "90 0.5 -1 30   45 2 10 -20", "90 0.5 -1 inf   45 2 10 -20"), 25, "NaN/Inf"),
        (lambda s: _broken(s, "90 0.5 -1 30   45 2 10 -20", "90 0.5 -1 abc   45 2 10 -20"), 25, "non-numeric"),
        (lambda s: _broken(s, "Frames: 2", "Frames: two"), 22, "integer"),
        (lambda s: _broken(s, "Frame Time: 0.04", "Frame Time: 0"), 23, "> 0"),
        (lambda s: _broken(s, "Frame Time: 0.04\n", ""), 23, "Frame Time"),
        (
            lambda s: _broken(s, "Yrotation Xposition Zposition Xrotation", "Yrotation Xposition Zposition Wrotation"),
            5,
            "unknown channel",
        ),
        # declared 4 channels but only 3 names: the parser reads 'JOINT' as the 4th
        (
            lambda s: _broken(
                s, "CHANNELS 4 Yrotation Xposition Zposition Xrotation", "CHANNELS 4 Yrotation Xposition Zposition"
            ),
            6,
            "unknown channel 'JOINT'",
        ),
        (lambda s: _broken(s, "CHANNELS 4 Yrotation", "CHANNELS 9 Yrotation"), 5, "0..6"),
        (lambda s: _broken(s, "OFFSET 0 1 0", "OFFSET 0 one 0"), 8, "expected a number"),
        (lambda s: _broken(s, "OFFSET 0 1 0", "OFFSET 0 NaN 0"), 8, "not finite"),
        (lambda s: _broken(s, "    CHANNELS 0\n  }\n}", "    CHANNELS 0\n  }\n"), 20, "unexpected end"),  # unbalanced
        (lambda s: _broken(s, "HIERARCHY", "HIERARCHIE"), 1, "HIERARCHY"),
    ],
)
def test_malformed_bvh_errors(tmp_path, mutate, line, words):
    p = _write(tmp_path, mutate(SMALL), "broken.bvh")
    with pytest.raises(SchemaError) as ei:
        read_bvh(p)
    e = ei.value
    assert e.file == str(p)
    assert words in str(e), str(e)
    if line is not None:
        assert e.field == f"line {line}", str(e)
    else:
        assert e.field


def test_missing_file(tmp_path):
    with pytest.raises(SchemaError, match="file not found"):
        read_bvh(tmp_path / "nope.bvh")


def test_extra_frame_rows_are_ignored_with_warning(tmp_path):
    p = _write(tmp_path, SMALL + "1 2 3 4 5 6 7 8\n")
    with pytest.warns(UserWarning, match=re.escape("beyond 'Frames: 2' ignored")):
        b = read_bvh(p)
    assert b.num_frames == 2


def test_other_skeleton_zxy_order():
    """assimp's Boxing_Toes.bvh: different skeleton, Z-X-Y channel order, 100 fps, one extra row."""
    p = BVH_DIR / "Boxing_Toes.bvh"
    if not p.exists():
        pytest.skip(f"{p} not installed")
    with pytest.warns(UserWarning):
        b = read_bvh(p)
    assert b.num_frames == 3069 and b.fps == pytest.approx(100.0) and b.num_joints == 21
    assert b.channels[1] == ["Zrotation", "Xrotation", "Yrotation"]
    G = bvh_global_transforms(b, [0, 1000])
    s = b.channel_start()[1]
    Rloc = Rotation.from_euler("ZXY", b.motion[[0, 1000], s : s + 3], degrees=True).as_matrix()
    np.testing.assert_allclose(G[:, 1, :3, :3], G[:, 0, :3, :3] @ Rloc, atol=1e-9)
