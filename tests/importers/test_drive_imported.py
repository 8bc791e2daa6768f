"""Driving what you imported: AMASS-style SMPL-X motion files on the (fake) SMPL-X rig, and one layout's fake
capture imported, prepared, trained (``tiny`` preset, 3 steps) and driven from BVH files (Biovision names; custom
names with a ``--joint-map``) and from an AMASS file through ``avatar-drive``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gsavatar.drive.cli import main as drive_main
from gsavatar.drive.motion import load_driving_motion
from gsavatar.geometry.lbs import lbs, skinning_transforms
from gsavatar.importers import load_smplx_model, smplx_template
from gsavatar.importers.smplx_model import SMPLX_JOINT_NAMES
from gsavatar.motion.amass import SMPLX_JOINT_ORDER, Z_UP_TO_Y_UP
from gsavatar.utils.errors import SchemaError
from importers.fake_smplx import write_fake_smplx

AMASS_TOL_M = 1e-5  # float32 motion arrays; observed ~1e-6 m


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return write_fake_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz", rings=4, segs=8)


@pytest.fixture(scope="module")
def body(model_path):
    b = smplx_template(load_smplx_model(model_path), np.zeros(10))
    return b.template, b.rig


def write_amass(path: Path, F: int = 9, fps: float | None = 60.0, seed: int = 0, width: int = 165, **extra) -> dict:
    """An AMASS-style SMPL-X file (random poses ~0.3 rad, translations ~0.5 m, the release's other keys)."""
    rng = np.random.default_rng(seed)
    arrays = {
        "poses": rng.normal(0, 0.3, (F, width)),
        "trans": rng.normal(0, 0.5, (F, 3)),
        "betas": rng.normal(0, 1, 16),
        "gender": np.array("neutral"),
        "surface_model_type": np.array("smplx"),
    }
    if fps is not None:
        arrays["mocap_frame_rate"] = np.array(fps)
    arrays |= extra
    np.savez(path, **arrays)
    return arrays


def surface(template, rig, pose, rr, rt) -> np.ndarray:
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
    T = skinning_transforms(rig, t(pose), t(rr), t(rt))
    return lbs(
        t(template.vertices), torch.as_tensor(template.skin_indices.astype(np.int64)), t(template.skin_weights), T
    ).numpy()


# --------------------------------------------------------------------------- AMASS
def test_amass_joint_order_is_the_importers():
    assert SMPLX_JOINT_ORDER == SMPLX_JOINT_NAMES


def test_amass_motion_on_the_smplx_rig(body, tmp_path):
    """60 fps AMASS file driven at 30 fps: every other source frame exactly; the posed surface is the one the
    file's own parameters give in AMASS's Z-up world, turned to Y up (x, z, -y)."""
    template, rig = body
    src = tmp_path / "walk_stageii.npz"
    a = write_amass(src)
    m = load_driving_motion(src, rig, 30.0)
    assert m.num_frames == 5 and m.fps == 30.0 and m.source_fps == 60.0 and m.face is None
    np.testing.assert_array_equal(m.pose, a["poses"][::2, 3:].astype(np.float32))
    ref = surface(template, rig, a["poses"][::2, 3:], a["poses"][::2, :3], a["trans"][::2]) @ Z_UP_TO_Y_UP.T
    ours = surface(template, rig, m.pose, m.root_rotation, m.root_translation)
    err = np.abs(ours - ref).max()
    assert err < AMASS_TOL_M, err
    assert np.abs(ref[..., 1] - ref[..., 2]).max() > 0.1  # the turn is visible (y and z differ)
    # up="y": taken as it is; --motion-fps overrides the file's rate (120 -> 30: every 4th frame)
    y = load_driving_motion(src, rig, 30.0, fps=120.0, amass_up="y")
    assert y.num_frames == 3
    np.testing.assert_array_equal(y.root_rotation, a["poses"][::4, :3].astype(np.float32))
    np.testing.assert_array_equal(y.root_translation, a["trans"][::4].astype(np.float32))
    # 60 -> 25 fps: the rotation-aware resampler (output frame 1 lies 2.4 source frames in)
    r = load_driving_motion(src, rig, 25.0, start=0, count=5)
    assert r.num_frames == 2
    from scipy.spatial.transform import Rotation, Slerp

    k = rig.joint_index("left_knee") - 1  # its parameter's index
    sl = Slerp([2, 3], Rotation.from_rotvec(a["poses"][2:4, 3 + 3 * k : 6 + 3 * k]))
    assert np.allclose(
        Rotation.from_rotvec(r.pose[1, 3 * k : 3 * k + 3]).as_matrix(), sl([2.4]).as_matrix()[0], atol=1e-6
    )


def test_amass_errors_name_file_and_key(body, tmp_path):
    _, rig = body
    f = tmp_path / "a.npz"
    write_amass(f, width=156)
    with pytest.raises(SchemaError, match=r"a\.npz: poses: expected shape \[F, 165\], got \[9, 156\]"):
        load_driving_motion(f, rig, 30.0)
    write_amass(f, fps=1e6)
    with pytest.raises(SchemaError, match="a.npz: mocap_frame_rate: .*outside the plausible range"):
        load_driving_motion(f, rig, 30.0)
    write_amass(f, fps=None)
    with pytest.raises(ValueError, match="frame rate unknown"):
        load_driving_motion(f, rig, 30.0)
    np.savez(f, poses=np.zeros((4, 165)), mocap_frame_rate=np.array(30.0))
    with pytest.raises(SchemaError, match="a.npz: trans: missing"):
        load_driving_motion(f, rig, 30.0)
    write_amass(f, poses=np.full((9, 165), np.nan))
    with pytest.raises(SchemaError, match="poses: 1485 NaN/Inf"):
        load_driving_motion(f, rig, 30.0)
    from motion.test_retarget_rigs import PRINCIPAL, euler_rig

    write_amass(f)
    with pytest.raises(SchemaError, match="drives SMPL-X rigs only"):
        load_driving_motion(f, euler_rig(rig, lambda j: PRINCIPAL), 30.0)


# --------------------------------------------------------------------------- end to end
@pytest.mark.slow  # ~50 s CPU, 100 s wall on 2 shared cores: project-uv's first (numba) run, training, 4 drives
def test_import_prepare_train_and_drive_from_bvh_and_amass(tmp_path, capsys):
    """THuman4.0-layout fake capture -> avatar-prep import -> avatar-prep all -> avatar-train avatar (tiny, 3 steps)
    + a 1-step predictor -> avatar-drive from a Biovision-named BVH, from custom names (refused, then driven with a
    --joint-map) and from an AMASS file, on one small orbit camera.

    The fake model carries UVs (``vt``/``ft``, as with ``--smplx-uvs``): without them ``avatar-prep all`` unwraps
    with xatlas, but sample-points keeps the template's (absent) UVs and training stops (reported, prep's code)."""
    from gsavatar.models.predictor import PredictorConfig
    from gsavatar.prep.cli import main as prep_main
    from gsavatar.train.cli import main as train_main
    from gsavatar.train.predictor import PredictorTrainConfig, train_predictor
    from importers.test_layouts import PREP_ARGS, make_source, run_import
    from motion.test_retarget_rigs import SPECS, bvh_from_spec

    model_path = write_fake_smplx(tmp_path / "smplx" / "SMPLX_NEUTRAL.npz", rings=4, segs=8, uv=True)
    src = tmp_path / "src"
    src.mkdir()
    make_source(src, "thuman4", model_path)
    cap, ds, run = tmp_path / "cap", tmp_path / "ds", tmp_path / "run"
    assert run_import("thuman4", src, model_path, cap) == 0
    assert prep_main(["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0
    assert (
        train_main(
            [
                "avatar",
                "--dataset",
                str(ds),
                "--out",
                str(run),
                "--preset",
                "tiny",
                "--steps",
                "3",
                "--lpips",
                "off",
                "--image-scale",
                "0.5",
                "--no-evaluate",
            ]
        )
        == 0
    )
    model = PredictorConfig(history=4, width=16, heads=2, ff=32, token_hidden=8, initial_hidden=16)
    train_predictor(
        run, PredictorTrainConfig(steps=1, batch_size=1, window=2, model=model), device="cpu", evaluate=False
    )

    from gsavatar.data_schema import load_capture

    rig = load_capture(cap).rig
    heads = rig.heads().astype(np.float64)
    common = [
        "--run",
        str(run),
        "--cameras",
        "orbit",
        "--orbit-views",
        "1",
        "--orbit-size",
        "32",
        "--lpips",
        "off",
        "--device",
        "cpu",
    ]
    # a Biovision-named BVH: limbs driven, spine2 and the hands/face listed in one warning line
    bvh = bvh_from_spec(tmp_path / "boxing_like.bvh", SPECS["biovision"][0], heads, F=12)
    out = tmp_path / "drive_bvh"
    capsys.readouterr()
    assert drive_main([*common, "--motion", str(bvh), "--count", "3", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "body joints ['spine2']" in err and "left_index1" in err
    info = json.loads((out / "drive.json").read_text())
    assert info["frames"] == 3 and len(info["motion_warnings"]) == 1
    z = np.load(out / "latents.npz")
    assert z["pose"].shape == (3, rig.pose_dim) and np.abs(z["pose"]).max() > 0.3
    frame = out / "frames" / "orbit00" / "000002.png"
    import cv2

    assert cv2.imread(str(frame)).max() > 0  # the avatar is in view
    # custom names: refused (exit 2, file and --joint-map named), then driven through a joint map
    base = SPECS["smplx"][0][:22]
    new = {n: f"bone{i}" for i, (n, _, _) in enumerate(base)}
    custom = bvh_from_spec(
        tmp_path / "custom.bvh", [(new[n], None if p is None else new[p], q) for n, p, q in base], heads
    )
    assert drive_main([*common, "--motion", str(custom), "--count", "2", "--out", str(tmp_path / "d2")]) == 2
    err = capsys.readouterr().err
    assert "custom.bvh" in err and "--joint-map" in err
    jm = tmp_path / "names.json"
    jm.write_text(json.dumps({n: v for n, v in new.items()}))
    assert (
        drive_main(
            [*common, "--motion", str(custom), "--joint-map", str(jm), "--count", "2", "--out", str(tmp_path / "d3")]
        )
        == 0
    )
    # AMASS at 60 fps -> the capture's 30 fps
    amass = tmp_path / "amass.npz"
    write_amass(amass, F=7)
    assert drive_main([*common, "--motion", str(amass), "--out", str(tmp_path / "d4")]) == 0
    info = json.loads((tmp_path / "d4" / "drive.json").read_text())
    assert info["frames"] == 4 and info["source_fps"] == 60.0 and info["fps"] == 30.0 and info["motion_warnings"] == []


@pytest.mark.slow  # ~60-100 s each on 2 shared cores
@pytest.mark.parametrize("layout", ["avatarrex", "actorshq"])
def test_other_layouts_prepare_train_and_drive(layout, tmp_path):
    """The other two layouts end to end: import -> prep all -> train (tiny, 3 steps) -> drive from a BVH."""
    from gsavatar.data_schema import load_capture
    from gsavatar.prep.cli import main as prep_main
    from gsavatar.train.cli import main as train_main
    from importers.test_layouts import PREP_ARGS, make_source, run_import
    from motion.test_retarget_rigs import SPECS, bvh_from_spec

    model_path = write_fake_smplx(tmp_path / "smplx" / "SMPLX_NEUTRAL.npz", rings=4, segs=8, uv=True)
    src = tmp_path / "src"
    src.mkdir()
    make_source(src, layout, model_path)
    cap, ds, run = tmp_path / "cap", tmp_path / "ds", tmp_path / "run"
    assert run_import(layout, src, model_path, cap) == 0
    assert prep_main(["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0
    assert (
        train_main(
            [
                "avatar",
                "--dataset",
                str(ds),
                "--out",
                str(run),
                "--preset",
                "tiny",
                "--steps",
                "3",
                "--lpips",
                "off",
                "--image-scale",
                "0.5",
                "--no-evaluate",
            ]
        )
        == 0
    )
    from gsavatar.models.predictor import PredictorConfig
    from gsavatar.train.predictor import PredictorTrainConfig, train_predictor

    model = PredictorConfig(history=4, width=16, heads=2, ff=32, token_hidden=8, initial_hidden=16)
    train_predictor(
        run, PredictorTrainConfig(steps=1, batch_size=1, window=2, model=model), device="cpu", evaluate=False
    )
    heads = load_capture(cap).rig.heads().astype(np.float64)
    bvh = bvh_from_spec(tmp_path / "smplx_names.bvh", SPECS["smplx"][0][:22], heads, F=6)
    out = tmp_path / "drive"
    assert (
        drive_main(
            [
                "--run",
                str(run),
                "--cameras",
                "orbit",
                "--orbit-views",
                "1",
                "--orbit-size",
                "32",
                "--lpips",
                "off",
                "--device",
                "cpu",
                "--motion",
                str(bvh),
                "--count",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    info = json.loads((out / "drive.json").read_text())
    assert info["frames"] == 2
    assert np.abs(np.load(out / "latents.npz")["pose"]).max() > 0.1  # the BVH drives the imported rig


@pytest.mark.slow  # ~60 s: xatlas unwrap, prep, 2 training steps
def test_smplx_import_without_uvs_trains(tmp_path):
    """Without the user's SMPL-X UV file uv-atlas unwraps the template with xatlas; sample-points must place
    the points in that layout (it used to keep the template's missing UVs and training stopped)."""
    from gsavatar.data_schema.hierarchy import Hierarchy
    from gsavatar.prep.cli import main as prep_main
    from gsavatar.train.cli import main as train_main
    from importers.test_layouts import PREP_ARGS, make_source, run_import

    model_path = write_fake_smplx(tmp_path / "smplx" / "SMPLX_NEUTRAL.npz", rings=4, segs=8, uv=False)
    src = tmp_path / "src"
    src.mkdir()
    make_source(src, "thuman4", model_path)
    cap, ds = tmp_path / "cap", tmp_path / "ds"
    assert run_import("thuman4", src, model_path, cap) == 0
    assert prep_main(["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0
    h = Hierarchy.load(ds / "sample_points" / "hierarchy.npz")
    atlas = np.load(ds / "uv_atlas" / "atlas.npz")
    assert h.anchors.uv is not None and np.isfinite(h.anchors.uv).all()
    assert atlas["uvs"].shape[0] > 0
    assert (
        train_main(
            [
                "avatar",
                "--dataset",
                str(ds),
                "--out",
                str(tmp_path / "run"),
                "--preset",
                "tiny",
                "--steps",
                "2",
                "--lpips",
                "off",
                "--image-scale",
                "0.5",
                "--no-evaluate",
            ]
        )
        == 0
    )
