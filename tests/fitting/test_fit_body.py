"""Body fit from multi-view keypoints: triangulation (closed form, one wrong view), the fit on a hand-made pose,
the keypoint readers and every bad-input kind of ``avatar-prep fit-body``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema.capture import Camera
from gsavatar.fitting.fit import FitConfig, fit_sequence, posed_keypoints
from gsavatar.fitting.keypoints import load_joint_map, packaged_joint_maps, read_keypoint_file, read_keypoints
from gsavatar.fitting.synthetic import synthetic_keypoints, write_openpose
from gsavatar.fitting.triangulate import camera_arrays, dlt, normalized_coords, project_world, triangulate
from gsavatar.geometry.camera import look_at
from gsavatar.utils.errors import SchemaError


def ring_cameras(n: int, radius: float = 3.0, size: int = 256, dist: bool = False) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.sin(a), 1.0 + 0.3 * (i % 2), radius * np.cos(a)])
        R, T = look_at(eye, np.array([0.0, 0.9, 0.0]))
        K = np.array([[300.0, 0, size / 2], [0, 300.0, size / 2], [0, 0, 1]])
        d = np.array([0.05, -0.01, 0.001, -0.001, 0.0]) if dist else np.zeros(5)
        cams.append(Camera(f"cam{i:02d}", K, R, T, d, size, size))
    return cams


def pixels(X: np.ndarray, cams: list[Camera]) -> np.ndarray:
    return project_world(X, cams)[0]  # [N, C, 2]


def test_dlt_two_views_closed_form():
    cams = ring_cameras(2)
    X = np.array([[0.1, 1.2, -0.3]])
    uv = pixels(X, cams)
    xy = np.stack([normalized_coords(uv[:, c], cams[c].K, None) for c in range(2)], 1)
    P = np.stack([np.concatenate([c.R, c.T[:, None]], 1) for c in cams])
    np.testing.assert_allclose(dlt(xy, np.ones((1, 2)), P), X, atol=1e-9)
    assert np.isnan(dlt(xy, np.array([[1.0, 0.0]]), P)).all()  # one view: unset


def test_triangulation_drops_the_one_wrong_view_with_distortion():
    cams = ring_cameras(5, dist=True)
    X = np.array([[0.0, 1.0, 0.1], [0.2, 0.5, -0.1]])
    uv = pixels(X, cams)  # [2, 5, 2]
    kp = np.zeros((1, 5, 2, 3))
    kp[0, :, :, :2] = uv.transpose(1, 0, 2)
    kp[0, :, :, 2] = 0.9
    kp[0, 3, 0, :2] += [60.0, -45.0]  # view 3 disagrees on point 0, confidently
    tri = triangulate(kp, cams)
    np.testing.assert_allclose(tri.points[0], X, atol=1e-6)
    assert tri.inliers[0, 0].tolist() == [True, True, True, False, True]
    assert tri.inliers[0, 1].all()
    assert tri.error_px[0].max() < 1e-4
    # averaging it in would have moved the point: the plain DLT over all five views
    xy = np.stack([normalized_coords(kp[0, c, :1, :2], cams[c].K, cams[c].dist) for c in range(5)], 1)
    P = np.stack([np.concatenate([c.R, c.T[:, None]], 1) for c in cams])
    assert np.linalg.norm(dlt(xy, np.ones((1, 5)), P)[0] - X[0]) > 0.01


def arm_setup():
    from tests.prep_fixtures import arm_rig

    rig = arm_rig()
    jmap = {
        "MidHip": ["Hips"],
        "Neck": ["Spine"],
        "LShoulder": ["LeftArm"],
        "LElbow": ["LeftForeArm"],
        "LWrist": ["LeftHand"],
        "LBigToe": ["LeftFinger"],
    }
    return rig, jmap


def param_slot(rig, name: str) -> int:
    """First pose slot of the rig parameter ``name``."""
    names = [p.name for p in rig.params]
    return sum(p.size for p in rig.params[: names.index(name)])


def write_map(tmp_path: Path, joints: dict) -> Path:
    from gsavatar.fitting.keypoints import resources

    base = json.loads(resources.files("gsavatar.fitting").joinpath("maps", "body25.json").read_text())
    p = tmp_path / "map.json"
    p.write_text(json.dumps({**base, "joints": joints}))
    return p


@pytest.mark.parametrize("ramp", [False, True])
def test_fit_recovers_a_hand_made_pose(tmp_path, ramp):
    import torch

    from gsavatar.geometry.lbs import pose_joints

    rig, jmap = arm_setup()
    jm = load_joint_map("body25", rig, write_map(tmp_path, jmap))
    cams = ring_cameras(6)
    F = 4
    pose = np.zeros((F, rig.pose_dim))
    off = lambda n: param_slot(rig, n)  # noqa: E731
    pose[:, off("Spine.rz")] = 0.3
    pose[:, off("LeftArm.ry")] = np.linspace(0.2, 0.5, F)
    pose[:, off("LeftForeArm.r") + 2] = np.linspace(0.4, 0.9, F)  # elbow bend
    pose[:, off("LeftHand.rz")] = -0.3
    rr = np.tile([0.0, 0.4, 0.0], (F, 1))
    tr = np.tile([0.1, 0.9, -0.2], (F, 1))
    J = pose_joints(rig, *(torch.as_tensor(a, dtype=torch.float64) for a in (pose, rr, tr))).numpy()
    kp = synthetic_keypoints(J[:, jm.joints], cams, jm, noise_px=0.0, outlier_fraction=0.0, drop_fraction=0.0)
    tri = triangulate(kp, cams)
    res = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(w_pose=1e-4, smooth_ramp=ramp))
    Jf = pose_joints(
        rig, *(torch.as_tensor(res[k], dtype=torch.float64) for k in ("pose", "root_rotation", "root_translation"))
    ).numpy()
    err_mm = 1000 * np.linalg.norm(Jf[:, jm.joints] - J[:, jm.joints], axis=-1)
    assert err_mm.mean() < 3.0, err_mm
    assert np.nanmax(res["reprojection_px"]) < 1.0
    if ramp:  # the ramp's root stage has no smoothness: the same as a fit without it
        cfg = dict(w_pose=1e-4, steps=0, root_steps=30)
        a = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(**cfg, smooth_ramp=True))
        b = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(**cfg, w_smooth=0.0, w_smooth_pose=0.0))
        c = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(**cfg))
        np.testing.assert_array_equal(a["root_rotation"], b["root_rotation"])
        assert np.abs(a["root_rotation"] - c["root_rotation"]).max() > 0  # while the plain root stage has it


def test_openpose_and_coco_wholebody_readers(tmp_path):
    a = np.arange(75, dtype=float).reshape(25, 3) / 100
    p = tmp_path / "00000003_keypoints.json"
    weak = np.full(75, 0.01)
    p.write_text(
        json.dumps({"people": [{"pose_keypoints_2d": weak.tolist()}, {"pose_keypoints_2d": a.ravel().tolist()}]})
    )
    got = read_keypoint_file(p, "body25")  # the more confident person; no hand / face arrays: not detected
    np.testing.assert_allclose(got[:25], a)
    assert got.shape == (137, 3) and not got[25:].any()
    hl, hr, face = (np.random.default_rng(k).uniform(0, 1, (n, 3)) for k, n in ((1, 21), (2, 21), (3, 70)))
    p.write_text(
        json.dumps(
            {
                "people": [
                    {
                        "pose_keypoints_2d": a.ravel().tolist(),
                        "hand_left_keypoints_2d": hl.ravel().tolist(),
                        "hand_right_keypoints_2d": hr.ravel().tolist(),
                        "face_keypoints_2d": face.ravel().tolist(),
                    }
                ]
            }
        )
    )
    np.testing.assert_allclose(read_keypoint_file(p, "body25"), np.concatenate([a, hl, hr, face]))
    # with several people, the most confident *body* wins: a bystander's detected face does not outweigh it
    subject = np.c_[a[:, :2], np.full(25, 0.9)]
    bystander = {"pose_keypoints_2d": np.c_[a[:, :2], np.full(25, 0.45)].ravel().tolist()}
    bystander["face_keypoints_2d"] = np.c_[face[:, :2], np.ones(70)].ravel().tolist()
    p.write_text(json.dumps({"people": [bystander, {"pose_keypoints_2d": subject.ravel().tolist()}]}))
    np.testing.assert_allclose(read_keypoint_file(p, "body25")[:25], subject)
    xy = np.random.default_rng(0).uniform(0, 100, (133, 2))
    sc = np.linspace(0.1, 1, 133)
    q = tmp_path / "c.json"
    q.write_text(json.dumps([{"keypoints": xy.tolist(), "keypoint_scores": sc.tolist()}]))
    np.testing.assert_allclose(read_keypoint_file(q, "coco_wholebody"), np.c_[xy, sc])
    parts = {"keypoints": 17, "foot_kpts": 6, "face_kpts": 68, "lefthand_kpts": 21, "righthand_kpts": 21}
    flat = np.c_[xy, sc]
    ann, k = {}, 0
    for key, n in parts.items():
        ann[key] = flat[k : k + n].ravel().tolist()
        k += n
    r = tmp_path / "d.json"
    r.write_text(json.dumps({"annotations": [ann]}))
    np.testing.assert_allclose(read_keypoint_file(r, "coco_wholebody"), flat)
    (tmp_path / "e.json").write_text(json.dumps({"people": []}))
    assert read_keypoint_file(tmp_path / "e.json", "body25") is None


@pytest.mark.parametrize(
    "kind", ["count", "hand_count", "hand_width", "nan", "json", "negative", "not_openpose", "camera"]
)
def test_bad_keypoint_files_name_the_file(tmp_path, kind):
    root = tmp_path / "kp"
    (root / "cam00").mkdir(parents=True)
    f = root / "cam00" / "00000000_keypoints.json"
    good = np.full((25, 3), 0.5)
    body = {"people": [{"pose_keypoints_2d": good.ravel().tolist()}]}
    if kind == "count":
        body["people"][0]["pose_keypoints_2d"] = good[:20].ravel().tolist()
    elif kind == "hand_count":
        body["people"][0]["hand_left_keypoints_2d"] = good[:20].ravel().tolist()
    elif kind == "hand_width":  # [[x, y], ...]: right count of numbers for 21 x 2, not [x, y, c]
        body["people"][0]["hand_left_keypoints_2d"] = np.full((21, 2), 0.5).tolist()
    elif kind == "nan":
        f.write_text(json.dumps(body).replace("0.5", "NaN", 1))
    elif kind == "negative":
        body["people"][0]["pose_keypoints_2d"][2] = -1.0
    elif kind == "not_openpose":
        body = {"persons": []}
    elif kind == "camera":
        (root / "cam99").mkdir()
    if kind == "json":
        f.write_text("{not json")
    elif kind != "nan":
        f.write_text(json.dumps(body))
    with pytest.raises(SchemaError) as e:
        read_keypoints(root, ["cam00"], [0], "body25")
    assert ("cam99" if kind == "camera" else "00000000_keypoints.json") in str(e.value)


# ----------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def tiny_fit_inputs(tiny_capture, tmp_path_factory):
    from gsavatar.data_schema import load_capture
    from gsavatar.synth.render import pose_joint_positions

    cap = load_capture(tiny_capture)
    names = sorted(cap.cameras)
    m = cap.motion
    J = pose_joint_positions(cap.rig, m.pose, m.root_rotation, m.root_translation)
    jm = load_joint_map("body25", cap.rig, template=cap.template)
    kp = synthetic_keypoints(
        posed_keypoints(cap.rig, jm, m.pose, m.root_rotation, m.root_translation),
        [cap.cameras[n] for n in names],
        jm,
        seed=1,
    )
    return cap, names, J, kp


def run_fit(capture: Path, kp_dir: Path, out: Path, *extra: str) -> int:
    from gsavatar.prep.cli import main

    return main(
        [
            "fit-body",
            "--capture",
            str(capture),
            "--keypoints",
            str(kp_dir),
            "--out",
            str(out),
            "--fit.steps",
            "300",
            "--fit.root-steps",
            "60",
            "--shard-frames",
            "6",
            *extra,
        ]
    )


def test_fit_body_writes_a_capture_that_prep_takes_and_resumes(tiny_capture, tiny_fit_inputs, tmp_path):
    from gsavatar.data_schema import load_capture

    cap, names, J, kp = tiny_fit_inputs
    kp = kp.copy()
    kp[:, 0] = 0.0  # camera 0 detects nobody: reported, not fatal
    kp[5] = 0.0  # the person is missing in every view of frame 5: a recorded skip
    kdir = tmp_path / "kp"
    write_openpose(kdir, kp, names, list(range(cap.num_frames)))
    out = tmp_path / "fitted"
    assert run_fit(tiny_capture, kdir, out) == 0
    fitted = load_capture(out)  # a valid capture v1
    assert fitted.num_frames == cap.num_frames and sorted(fitted.cameras) == names
    rep = json.loads((out / "fit" / "report.json").read_text())
    assert rep["skipped_frames"] == [5]
    assert rep["views_without_detections"][names[0]] == cap.num_frames
    assert (out / "fit" / "overlay.png").is_file() and rep["reprojection_px"]["mean"] < 10.0  # 300 steps only
    from gsavatar.synth.render import pose_joint_positions

    m = fitted.motion
    Jf = pose_joint_positions(fitted.rig, m.pose, m.root_rotation, m.root_translation)
    jm = load_joint_map("body25", cap.rig)
    assert 1000 * np.linalg.norm(Jf[:, jm.joints] - J[:, jm.joints], axis=-1).mean() < 40.0
    before = {p: p.stat().st_mtime_ns for p in (out / "fit" / "shards").iterdir()}
    assert run_fit(tiny_capture, kdir, out) == 0  # resumes: every shard reused
    assert json.loads((out / "fit" / "report.json").read_text())["shards"]["reused"] == len(before)
    assert {p: p.stat().st_mtime_ns for p in (out / "fit" / "shards").iterdir()} == before


def test_fit_body_bad_inputs_exit_non_zero_and_write_nothing(tiny_capture, tiny_fit_inputs, tmp_path, capsys):
    cap, names, _, kp = tiny_fit_inputs
    out = tmp_path / "out"
    assert run_fit(tiny_capture, tmp_path / "missing", out) != 0
    assert "keypoint" in capsys.readouterr().err and not out.exists()
    empty = tmp_path / "empty"
    write_openpose(empty, np.zeros_like(kp), names, list(range(cap.num_frames)))
    assert run_fit(tiny_capture, empty, out) != 0
    assert "no detections" in capsys.readouterr().err and not out.exists()
    assert run_fit(tiny_capture, empty, tiny_capture) != 0  # never over the input


def test_torch_projection_matches_the_numpy_camera_model():
    import torch

    from gsavatar.fitting.fit import _project
    from gsavatar.geometry.camera import project

    cams = ring_cameras(3, dist=True)
    X = np.random.default_rng(0).uniform([-0.5, 0.2, -0.5], [0.5, 1.8, 0.5], (2, 7, 3))  # [F, M, 3]
    Ks, Rs, Ts, ds = (torch.as_tensor(a) for a in camera_arrays(cams))
    pix, z = _project(torch.as_tensor(X), Ks, Rs, Ts, ds)
    for c, cam in enumerate(cams):
        ref = project(X.reshape(-1, 3), cam.K, cam.R, cam.T, cam.dist)
        np.testing.assert_allclose(pix[:, c].reshape(-1, 2).numpy(), ref.pixels, atol=1e-9)
        np.testing.assert_allclose(z[:, c].reshape(-1).numpy(), ref.depth, atol=1e-12)


def test_marker_keypoints_ride_rigidly_on_their_joint():
    from types import SimpleNamespace

    import torch

    from gsavatar.fitting.fit import keypoint_points
    from gsavatar.fitting.keypoints import marker_offset
    from gsavatar.geometry.lbs import RigTensors, lbs, skinning_transforms

    rig, _ = arm_setup()
    heads = rig.heads().astype(np.float64)
    j = [x.name for x in rig.joints].index("LeftHand")
    # four vertices skinned fully to LeftHand, one to LeftArm; the hand's farthest along +y and along its bone
    V = heads[j] + np.array(
        [[0.0, 0.05, 0.0], [0.0, -0.02, 0.01], [0.08, 0.0, 0.0], [0.02, 0.0, 0.03], [0.0, 0.3, 0.0]]
    )
    si = np.array([[j, 0], [j, 0], [j, 0], [j, 0], [2, 0]])
    sw = np.array([[1.0, 0.0]] * 4 + [[1.0, 0.0]])
    tpl = SimpleNamespace(vertices=V, skin_indices=si, skin_weights=sw)
    np.testing.assert_allclose(marker_offset(rig, tpl, j, "+y"), [0.0, 0.05, 0.0])  # not the LeftArm vertex
    np.testing.assert_allclose(marker_offset(rig, tpl, j, "bone"), [0.08, 0.0, 0.0])  # the arm runs along +x
    g = torch.Generator().manual_seed(0)
    pose = 0.5 * torch.randn(3, rig.pose_dim, generator=g, dtype=torch.float64)
    rr, tr = (
        0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64),
        torch.randn(3, 3, generator=g, dtype=torch.float64),
    )
    off = torch.as_tensor(V[:1] - heads[j])
    got = keypoint_points(RigTensors(rig, dtype=torch.float64), torch.tensor([j]), off, pose, rr, tr)[:, 0]
    T = skinning_transforms(rig, pose, rr, tr)
    ref = torch.stack(
        [
            lbs(torch.as_tensor(V[:1]), torch.as_tensor(si[:1]), torch.as_tensor(sw[:1]), T[i : i + 1]).reshape(-1, 3)[
                0
            ]
            for i in range(3)
        ]
    )
    torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)


def fake_smplx_capture(root: Path, model, F: int, cams: list[Camera]) -> Path:
    """A capture whose body is the fake SMPL-X model at its mean shape, as `avatar-prep import` writes one (images
    are noise: the fit reads only cameras and keypoints)."""
    from gsavatar.data_schema import Motion, Split, write_capture_metadata
    from gsavatar.data_schema.template import save_template
    from gsavatar.importers.smplx_body import smplx_template
    from gsavatar.utils.io import write_image

    body = smplx_template(model, np.zeros(10))
    save_template(body.template, root / "template")
    body.rig.save(root / "template" / "rig.json")
    names = [c.name for c in cams]
    write_capture_metadata(
        root,
        30.0,
        F,
        {c.name: c for c in cams},
        {"train": Split(list(range(F - 1)), names[:-1]), "test": Split([F - 1], names[-1:])},
    )
    z = np.zeros((F, 3), np.float32)
    Motion(np.zeros((F, body.rig.pose_dim), np.float32), z, z).save(root / "motion.npz")
    rng = np.random.default_rng(0)
    for c in cams:
        for f in range(F):
            write_image(root / "images" / c.name / f"{f:08d}.png", rng.random((c.height, c.width, 3)))
            write_image(root / "masks" / c.name / f"{f:08d}.png", np.ones((c.height, c.width), np.float32))
    return root


def test_fit_body_smplx_model_fits_the_shape_and_writes_its_template(tmp_path):
    """`fit-body --smplx-model` on a capture of the fake SMPL-X body (tests/importers/fake_smplx.py) at its mean
    shape, with noiseless COCO-WholeBody keypoints of the body at a known shape (10 betas in [-3, 3]) in known poses
    seen by 8 cameras: the written template is the model at the recovered betas, the rig's heads are the shape's,
    the poses reproduce the joints, far better than the same fit without the shape; a re-run reuses the shape and
    the shards."""
    import torch

    from gsavatar.data_schema import load_capture
    from gsavatar.fitting.synthetic import write_coco_wholebody
    from gsavatar.geometry.lbs import pose_joints
    from gsavatar.importers.smplx_body import shaped_vertices, smplx_rig, smplx_shape_basis
    from gsavatar.importers.smplx_model import load_smplx_model
    from importers.fake_smplx import write_fake_smplx

    model_file = write_fake_smplx(tmp_path / "SMPLX_NEUTRAL.npz", rings=4, segs=8)
    model = load_smplx_model(model_file)
    heads0, dheads = smplx_shape_basis(model, 10)
    betas = np.random.default_rng(3).uniform(-3.0, 3.0, 10)
    true_rig = smplx_rig(model, heads0 + np.einsum("b,bjk->jk", betas, dheads))
    F = 6
    pose = np.zeros((F, true_rig.pose_dim))
    names = [p.name for p in true_rig.params]
    for j, amp in (("left_shoulder", 0.5), ("right_elbow", 0.8), ("left_knee", 0.6), ("spine1", 0.2)):
        s = sum(p.size for p in true_rig.params[: names.index(f"{j}.aa")])
        pose[:, s : s + 3] = amp * np.sin(np.linspace(0, 2, F))[:, None] * np.array([1.0, 0.3, -0.5])
    rr, tr = np.tile([0.0, 0.4, 0.0], (F, 1)), np.tile([0.05, 1.4, -0.1], (F, 1))
    t64 = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    J = pose_joints(true_rig, t64(pose), t64(rr), t64(tr)).numpy()
    cams = ring_cameras(8, radius=2.5)
    cap_dir = fake_smplx_capture(tmp_path / "cap", model, F, cams)
    jm = load_joint_map("coco_wholebody", true_rig)
    kp = synthetic_keypoints(J[:, jm.joints], cams, jm, noise_px=0.0, outlier_fraction=0.0, drop_fraction=0.0)
    kdir = tmp_path / "kp"
    write_coco_wholebody(kdir, kp, [c.name for c in cams], list(range(F)))
    out = tmp_path / "fitted"
    flags = ["--fit.w-pose", "1e-5", "--fit.w-shape", "1e-6", "--fit.steps", "400"]
    shape = ["--smplx-model", str(model_file), "--shape-frames", "6", "--shape-steps", "1500"]
    assert run_fit(cap_dir, kdir, out, *flags, *shape) == 0
    fitted = load_capture(out)
    rep = json.loads((out / "fit" / "report.json").read_text())
    got = np.array(rep["shape"]["betas"])
    verts_err_mm = 1000 * np.abs(fitted.template.vertices - shaped_vertices(model, betas)).max()
    heads_err_mm = 1000 * np.linalg.norm(fitted.rig.heads() - true_rig.heads(), axis=-1).mean()
    m = fitted.motion
    Jf = pose_joints(fitted.rig, t64(m.pose), t64(m.root_rotation), t64(m.root_translation)).numpy()
    err_mm = 1000 * np.linalg.norm(Jf[:, jm.joints] - J[:, jm.joints], axis=-1).mean()
    assert run_fit(cap_dir, kdir, tmp_path / "no_shape", *flags) == 0
    m = load_capture(tmp_path / "no_shape").motion
    Jn = pose_joints(load_capture(cap_dir).rig, t64(m.pose), t64(m.root_rotation), t64(m.root_translation)).numpy()
    err_no_shape_mm = 1000 * np.linalg.norm(Jn[:, jm.joints] - J[:, jm.joints], axis=-1).mean()
    print(
        f"fit-body --smplx-model: |beta error| mean {np.abs(got - betas).mean():.3f} max "
        f"{np.abs(got - betas).max():.3f}, template vertices max {verts_err_mm:.2f} mm, rest heads "
        f"{heads_err_mm:.2f} mm, joints {err_mm:.2f} mm "
        f"(without the shape {err_no_shape_mm:.2f} mm)"
    )
    assert np.abs(got - betas).max() < 0.15 and heads_err_mm < 2.0 and err_mm < 2.0 and verts_err_mm < 10.0
    assert err_no_shape_mm > 5 * err_mm
    assert not (out / "template" / "mesh.obj").is_symlink()  # written, the input's template untouched
    assert np.abs(load_capture(cap_dir).template.vertices - shaped_vertices(model, np.zeros(10))).max() < 1e-6
    np.testing.assert_array_equal(fitted.template.faces, model.faces)
    before = (out / "fit" / "shape.npz").stat().st_mtime_ns
    assert run_fit(cap_dir, kdir, out, *flags, *shape) == 0
    rep = json.loads((out / "fit" / "report.json").read_text())
    assert rep["shape"]["reused"] and rep["shards"]["reused"] == rep["shards"]["total"]
    assert (out / "fit" / "shape.npz").stat().st_mtime_ns == before


def test_fit_body_smplx_model_refuses_a_capture_of_another_body(tiny_capture, tiny_fit_inputs, tmp_path, capsys):
    from importers.fake_smplx import write_fake_smplx

    cap, names, _, kp = tiny_fit_inputs
    kdir = tmp_path / "kp"
    write_openpose(kdir, kp, names, list(range(cap.num_frames)))
    model_file = write_fake_smplx(tmp_path / "SMPLX_NEUTRAL.npz", rings=4, segs=8)
    out = tmp_path / "out"
    assert run_fit(tiny_capture, kdir, out, "--smplx-model", str(model_file)) != 0
    err = capsys.readouterr().err
    assert "rig.json" in err and "not an SMPL-X rig" in err and not out.exists()
    assert run_fit(tiny_capture, kdir, out, "--smplx-model", str(tmp_path / "missing.npz")) != 0
    assert "missing.npz" in capsys.readouterr().err and not out.exists()


# ----------------------------------------------------------------------------- silhouette term
def test_silhouette_distance_matches_brute_force():
    from gsavatar.fitting.fit import silhouette_distance

    rng = np.random.default_rng(0)
    mask = np.zeros((23, 31), np.float32)
    mask[5:12, 8:20] = 1.0
    mask[rng.integers(0, 23, 6), rng.integers(0, 31, 6)] = 1.0
    d = silhouette_distance(mask, (31, 23))
    fg = np.argwhere(mask >= 0.5)
    yy, xx = np.mgrid[:23, :31]
    ref = np.sqrt(((np.stack([yy, xx], -1)[:, :, None] - fg[None, None]) ** 2).sum(-1)).min(-1)
    np.testing.assert_allclose(d, ref, atol=1e-3)  # DIST_MASK_PRECISE is exact Euclidean
    assert np.isnan(silhouette_distance(np.zeros((8, 8)), (4, 4))).all()  # an empty mask says nothing


def test_silhouette_loss_against_a_linear_distance_map():
    """Bilinear sampling of a distance map linear in u is exact: the loss is the Geman-McClure mean of the
    hand-computed distances of the projected points (pixel centres at +0.5, the renderer's); points behind the
    camera and maps of NaN (no mask) are skipped."""
    import torch

    from gsavatar.fitting.fit import Silhouette, geman_mcclure, silhouette_loss
    from gsavatar.fitting.triangulate import camera_arrays
    from gsavatar.geometry.lbs import RigTensors
    from gsavatar.data_schema.rig import Joint, PoseParam, Rig

    rig = Rig([Joint("root", None, (0.0, 0.0, 0.0))], [PoseParam("root.rx", "root", "euler", (1.0, 0.0, 0.0))], {})
    cams = ring_cameras(2)
    pts = np.array([[0.0, 0.9, 0.0], [0.2, 1.1, 0.1], [-0.3, 0.7, 0.2]])
    pix = pixels(pts, cams)  # [N, C, 2]
    W = 256
    u = np.arange(W) + 0.5  # pixel centres
    lin = np.maximum(0.0, u - 120.0)  # distance grows to the right of u = 30
    dist = np.broadcast_to(lin, (1, 2, W, W)).astype(np.float32).copy()
    dist[0, 1] = np.nan  # camera 1 has no mask in this frame
    sil = Silhouette(pts, np.zeros((3, 1), int), np.ones((3, 1)), dist, np.array([[W, W], [W, W]]))
    z = torch.zeros(1, 3, dtype=torch.float64)
    pose = torch.zeros(1, 1, dtype=torch.float64)
    arrs = tuple(torch.as_tensor(a, dtype=torch.float64) for a in camera_arrays(cams))
    got = silhouette_loss(RigTensors(rig, dtype=torch.float64), sil, pose, z, z, arrs, sigma=4.0)
    ref = geman_mcclure(torch.as_tensor(np.maximum(0.0, pix[:, 0, 0] - 120.0) ** 2), 4.0).mean()
    assert 0.5 <= pix[:, 0, 0].min() and pix[:, 0, 0].max() <= W - 0.5  # inside: no border clamping involved
    assert float(ref) > 1.0  # some points lie right of u = 120: the term is not trivially zero
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)


def test_fit_body_silhouette_refuses_a_missing_mask_before_writing(tiny_capture, tiny_fit_inputs, tmp_path, capsys):
    import shutil

    cap, names, _, kp = tiny_fit_inputs
    kdir = tmp_path / "kp"
    write_openpose(kdir, kp, names, list(range(cap.num_frames)))
    copy = tmp_path / "cap"
    shutil.copytree(tiny_capture, copy)
    gone = copy / "masks" / names[1] / f"{3:08d}.png"
    gone.unlink()
    out = tmp_path / "out"
    assert run_fit(copy, kdir, out, "--fit.w-silhouette", "1") == 2
    assert str(gone) in capsys.readouterr().err and not out.exists()
    assert run_fit(tiny_capture, kdir, out, "--fit.w-silhouette", "1", "--silhouette-points", "0") == 2
    assert "--silhouette-points" in capsys.readouterr().err and not out.exists()


def test_body25_maps_may_list_the_body_only_and_hands_index_after_it(tmp_path):
    rig, jmap = arm_setup()
    base = json.loads(write_map(tmp_path, jmap).read_text())
    assert len(base["names"]) == 137 and base["names"][25] == "hand_left_0" and base["names"][67] == "face_0"
    short = tmp_path / "short.json"
    short.write_text(json.dumps({**base, "names": base["names"][:25]}))  # a map of the 25 body keypoints
    jm = load_joint_map("body25", rig, short)
    assert jm.names == tuple(jmap) and list(jm.keypoints) == [base["names"].index(n) for n in jmap]
    hands = tmp_path / "hands.json"  # a hand point from OpenPose's hand array: keypoint 25 + 9
    hands.write_text(json.dumps({**base, "joints": {**jmap, "hand_left_9": ["LeftFinger"]}}))
    assert load_joint_map("body25", rig, hands).keypoints[-1] == 34
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**base, "names": base["names"][:30]}))
    with pytest.raises(SchemaError, match="25 or 137"):
        load_joint_map("body25", rig, bad)


def test_the_documented_hand_map_loads_on_the_synthetic_body(tiny_capture):
    """The packaged map ``body25_hands`` (the opt-in hand points of docs/fit_body.md) maps all its keypoints on
    anny, by name as ``--joint-map body25_hands``."""
    from gsavatar.data_schema import load_capture

    cap = load_capture(tiny_capture)
    assert {"body25", "body25_hands", "coco_wholebody"} <= set(packaged_joint_maps())
    jm = load_joint_map("body25", cap.rig, "body25_hands", template=cap.template)
    default = load_joint_map("body25", cap.rig, template=cap.template)
    assert len(jm.names) == len(default.names) + 6 and {"hand_left_9", "hand_right_4"} <= set(jm.names)
    assert set(jm.keypoints[len(default.names) :]) <= set(range(25, 67))  # from the hand arrays


def test_pose_prior_mean_decides_what_no_keypoint_sees(tmp_path):
    """LeftFinger's own rotation moves no mapped point: the fit keeps it at the prior's centre, which is the rest
    pose by default and the true value when the prior's mean carries it; the seen joints fit either way."""
    import torch

    from gsavatar.geometry.lbs import pose_joints

    rig, jmap = arm_setup()
    jm = load_joint_map("body25", rig, write_map(tmp_path, jmap))
    cams = ring_cameras(6)
    F = 3
    off = lambda n: param_slot(rig, n)  # noqa: E731
    pose = np.zeros((F, rig.pose_dim))
    pose[:, off("LeftArm.ry")] = 0.3
    pose[:, off("LeftForeArm.r") + 2] = 0.6
    pose[:, off("LeftFinger.rx")] = 0.7  # unobserved
    rr, tr = np.zeros((F, 3)), np.tile([0.0, 0.9, 0.0], (F, 1))
    J = pose_joints(rig, *(torch.as_tensor(a, dtype=torch.float64) for a in (pose, rr, tr))).numpy()
    kp = synthetic_keypoints(J[:, jm.joints], cams, jm, noise_px=0.0, outlier_fraction=0.0, drop_fraction=0.0)
    tri = triangulate(kp, cams)
    mu = np.zeros(rig.pose_dim)
    mu[off("LeftFinger.rx")] = 0.7
    for prior, want in ((None, 0.0), (mu, 0.7)):
        res = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(w_pose=1e-4), prior_mean=prior)
        assert np.allclose(res["pose"][:, off("LeftFinger.rx")], want, atol=1e-3)
        Jf = pose_joints(
            rig, *(torch.as_tensor(res[k], dtype=torch.float64) for k in ("pose", "root_rotation", "root_translation"))
        ).numpy()
        assert 1000 * np.linalg.norm(Jf[:, jm.joints] - J[:, jm.joints], axis=-1).mean() < 3.0
    with pytest.raises(ValueError, match="prior_mean"):
        fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(steps=1), prior_mean=mu[:-1])


def test_pose_prior_spread_resolves_what_the_keypoints_cannot_see(tmp_path):
    """On the arm (every keypoint on one line at rest) a twist about that line moves no keypoint until the elbow
    bends, and then the upper arm's twist, the forearm's and the hand's trade with each other and with the root.
    A prior whose motion only ever moves the three parameters the truth moves (spread 1 rad there, 0 elsewhere: the
    floor applies) recovers the limb's rotations; a prior of 1 rad everywhere (no spread) fits the points as well
    but not the rotations."""
    import torch

    from gsavatar.geometry.lbs import skinning_transforms

    from types import SimpleNamespace

    rig, jmap = arm_setup()
    # a marker 10 cm above the spine's head pins the roll of the whole chain about its line (the root's)
    spine = rig.joint_index("Spine")
    tpl = SimpleNamespace(
        vertices=rig.heads()[spine][None] + [[0.0, 0.1, 0.0]],
        skin_indices=np.array([[spine]]),
        skin_weights=np.array([[1.0]]),
    )
    jmap = {**jmap, "RShoulder": {"joints": ["Spine"], "extreme": "+y"}}
    jm = load_joint_map("body25", rig, write_map(tmp_path, jmap), template=tpl)
    cams = ring_cameras(6)
    F = 3
    off = lambda n: param_slot(rig, n)  # noqa: E731
    moved = [off("LeftArm.rx"), off("LeftForeArm.r") + 2, off("LeftHand.rz")]
    pose = np.zeros((F, rig.pose_dim))
    pose[:, moved] = [0.5, 0.6, 0.4]  # upper-arm twist (the bone runs along +x), elbow bend, wrist bend
    rr, tr = np.zeros((F, 3)), np.tile([0.0, 0.9, 0.0], (F, 1))
    t = lambda *a: [torch.as_tensor(x, dtype=torch.float64) for x in a]  # noqa: E731
    J = posed_keypoints(rig, jm, pose, rr, tr)
    kp = synthetic_keypoints(J, cams, jm, noise_px=0.0, outlier_fraction=0.0, drop_fraction=0.0)
    tri = triangulate(kp, cams)
    limb = [rig.joint_index(n) for n in ("LeftArm", "LeftForeArm", "LeftHand")]
    R_true = skinning_transforms(rig, *t(pose, rr, tr))[:, limb, :3, :3].numpy()
    std = np.zeros(rig.pose_dim)
    std[moved] = 1.0
    angle = {}
    for name, spread in (("spread", std), ("flat", None)):
        res = fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(), prior_std=spread)
        fitted = t(*(res[k] for k in ("pose", "root_rotation", "root_translation")))
        Jf = posed_keypoints(rig, jm, *(res[k] for k in ("pose", "root_rotation", "root_translation")))
        assert 1000 * np.linalg.norm(Jf - J, axis=-1).mean() < 3.0  # both fit the points
        R = skinning_transforms(rig, *fitted)[:, limb, :3, :3].numpy()
        cos = (np.einsum("fjab,fjab->fj", R, R_true) - 1) / 2
        angle[name] = np.degrees(np.arccos(np.clip(cos, -1, 1)))  # [F, 3] global rotation error per limb joint
    assert angle["spread"].max() < 5.0, angle  # measured 0.9-3.9 deg
    assert angle["flat"].min() > 20.0, angle  # measured 27-35 deg: the twist went elsewhere
    with pytest.raises(ValueError, match="prior_std"):
        fit_sequence(rig, cams, kp, jm, tri.points, tri.inliers, FitConfig(steps=1), prior_std=-std)


def test_prior_statistics_do_not_mix_euler_branches(tmp_path):
    """The same rotations written in the other Euler branch ``(a + pi, pi - b, c + pi)`` (and shifted by 2 pi) on half
    the frames, as a retargeted motion does after a near-gimbal frame: the prior's mean and spread are those of the
    un-aliased motion, and canonical_poses keeps every frame's rotations."""
    import torch

    from gsavatar.fitting.prior import canonical_poses, pose_prior_stats
    from gsavatar.geometry.lbs import pose_to_local_rotations

    rig, _ = arm_setup()
    g = np.random.default_rng(0)
    F = 40
    pose = np.zeros((F, rig.pose_dim))
    arm = [param_slot(rig, f"LeftArm.{a}") for a in ("rx", "ry", "rz")]
    pose[:, arm] = [0.3, -0.2, 0.5] + 0.1 * g.standard_normal((F, 3))
    aliased = pose.copy()
    a, b, c = (pose[F // 2 :, k] for k in arm)
    aliased[F // 2 :, arm] = np.stack([a + np.pi, np.pi - b, c + np.pi - 2 * np.pi], -1)
    L = lambda p: pose_to_local_rotations(torch.as_tensor(p), rig).numpy()  # noqa: E731
    np.testing.assert_allclose(L(aliased), L(pose), atol=1e-12)  # the same motion
    assert np.abs(aliased.mean(0) - pose.mean(0)).max() > 1.0  # whose raw angle mean is meaningless
    np.testing.assert_allclose(canonical_poses(aliased, rig), pose, atol=1e-9)
    p = tmp_path / "aliased.npz"
    np.savez(p, pose=aliased)
    mean, std, _ = pose_prior_stats([p], rig)
    np.testing.assert_allclose(mean, pose.mean(0), atol=1e-9)
    np.testing.assert_allclose(std, pose.std(0), atol=1e-9)


@pytest.mark.parametrize("kind", ["missing", "suffix", "shape", "nan", "no_pose"])
def test_bad_pose_prior_files_name_the_file(tmp_path, kind):
    from gsavatar.fitting.prior import pose_prior_mean

    rig, _ = arm_setup()
    p = tmp_path / ("prior.txt" if kind == "suffix" else "prior.npz")
    pose = np.zeros((5, rig.pose_dim))
    if kind == "shape":
        pose = pose[:, :-1]
    elif kind == "nan":
        pose[2, 1] = np.nan
    if kind == "no_pose":
        np.savez(p, motion=pose)
    elif kind != "missing":
        np.savez(p, pose=pose) if kind != "suffix" else p.write_text("0")
    with pytest.raises(SchemaError) as e:
        pose_prior_mean([p], rig)
    assert p.name in str(e.value)
    q = tmp_path / "ok.npz"
    np.savez(q, pose=np.full((4, rig.pose_dim), 0.25))
    mean, entry = pose_prior_mean([q, q], rig)
    assert np.allclose(mean, 0.25) and entry["frames"] == 8
    from gsavatar.fitting.prior import pose_prior_stats

    np.savez(q, pose=np.stack([np.full(rig.pose_dim, 0.25), np.full(rig.pose_dim, 0.75)]))
    mean, std, entry = pose_prior_stats([q], rig)
    assert np.allclose(mean, 0.5) and np.allclose(std, 0.25) and entry["frames"] == 2


@pytest.mark.skipif(
    not Path("/usr/share/assimp/models/BVH/01_03.bvh").exists(), reason="needs Debian's assimp-testmodels"
)
def test_fit_body_pose_prior_from_bvh_is_reported_and_refits(tiny_capture, tiny_fit_inputs, tmp_path, capsys):
    """--pose-prior with a real CMU BVH (retargeted onto the capture's rig): reported, and part of the shards'
    fingerprint (the same keypoints without it refit every shard); a bad prior file writes nothing."""
    cap, names, _, kp = tiny_fit_inputs
    kdir = tmp_path / "kp"
    write_openpose(kdir, kp, names, list(range(cap.num_frames)))
    bvh = "/usr/share/assimp/models/BVH/01_03.bvh"
    out = tmp_path / "fitted"
    assert run_fit(tiny_capture, kdir, out, "--pose-prior", bvh) == 0
    rep = json.loads((out / "fit" / "report.json").read_text())
    assert rep["pose_prior"]["files"] == [bvh] and rep["pose_prior"]["frames"] > 100
    assert run_fit(tiny_capture, kdir, out) == 0
    assert json.loads((out / "fit" / "report.json").read_text())["shards"]["reused"] == 0
    bad = tmp_path / "bad"
    assert run_fit(tiny_capture, kdir, bad, "--pose-prior", str(tmp_path / "none.bvh")) != 0
    assert "none.bvh" in capsys.readouterr().err and not bad.exists()


def test_joint_map_names_files_first_and_clear_errors(tmp_path, monkeypatch):
    """``--joint-map NAME``: an existing file of that name wins over the packaged map; an unknown name, a folder
    and a packaged map of another format are refused naming the map."""
    rig, jmap = arm_setup()
    monkeypatch.chdir(tmp_path)
    own = write_map(tmp_path, jmap)
    Path("body25_hands").write_text(own.read_text())  # a user's file that happens to carry the packaged name
    assert load_joint_map("body25", rig, "body25_hands").names == load_joint_map("body25", rig, own).names
    with pytest.raises(SchemaError, match="packaged maps by name: .*body25_hands"):
        load_joint_map("body25", rig, "no_such_map")
    Path("a_folder").mkdir()
    with pytest.raises(SchemaError, match="a_folder.*cannot be read"):
        load_joint_map("body25", rig, "a_folder")
    with pytest.raises(SchemaError, match="coco_wholebody.json.*is a map for 'coco_wholebody'"):
        load_joint_map("body25", rig, "coco_wholebody")
