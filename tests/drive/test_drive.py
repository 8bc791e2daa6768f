"""avatar-drive: motion loading (npz / capture / BVH), frame-rate resampling, streaming == batch,
latent sources (the drive-mode table, a mode defined here), metrics + figure 7, the CLI end to end,
the latent-source comparison figure, and bad inputs (exit code 2, message names file + field)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro
from scipy.spatial.transform import Rotation

from gsavatar.data_schema import SchemaError, load_capture
from gsavatar.drive.cli import main
from gsavatar.drive.driver import DriveConfig, Driver, FrameInputs, motion_inputs
from gsavatar.drive.metrics import SequenceMetrics, measure_ramp_up, write_ramp_up
from gsavatar.drive.motion import load_driving_motion
from gsavatar.drive.sources import LATENT_SOURCES, DriveMode, LatentSource, ramp_up_modes
from gsavatar.motion.resample import _joint_layouts, resample_motion
from gsavatar.models.batch import FrameBatch
from gsavatar.models.predictor import AppearancePredictor, PredictorConfig

BVH = Path("/usr/share/assimp/models/BVH/01_01.bvh")


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def tiny_run(tiny_dataset, tmp_path_factory) -> Path:
    from gsavatar.train.cli import main as train_main

    run = tmp_path_factory.mktemp("drive") / "run"
    assert (
        train_main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
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
    return run


@pytest.fixture(scope="module")
def loaded(tiny_run):
    from gsavatar.runs.load import load_run

    return load_run(tiny_run, "cpu")


def small_predictor(net, trained_init: bool = False) -> AppearancePredictor:
    """An untrained (random) predictor of the real class, small enough for tests."""
    av = net.avatar
    cfg = PredictorConfig(
        history=4,
        width=16,
        heads=2,
        ff=32,
        latent_dim=av.latent_in,
        token_hidden=8,
        latent_pca_components=4,
        initial_hidden=16,
    )
    p = AppearancePredictor(cfg, av.num_anchors, np.arange(0, av.pose_dim, 5), av.pose_dim, seed=1).eval()
    torch.nn.init.normal_(p.head.weight, std=0.1)  # the residual head starts at zero (persistence); move it
    if trained_init:
        torch.nn.init.normal_(p.initial.net[-1].weight, std=0.1)
        p.initial_ready.fill_(True)
    return p


# --------------------------------------------------------------------------- resampling
def _constant_velocity_motion(rig, n: int, fps: float, seed: int = 0):
    """Every joint / the root turns at a constant angular velocity about a fixed local axis,
    translation and face move linearly: slerp/lerp midpoints of this are exact."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fps
    pose = np.zeros((n, rig.pose_dim))
    for kind, sl, seq, signs in _joint_layouts(rig):
        base = Rotation.from_rotvec(rng.normal(scale=0.3, size=3))
        R = base * Rotation.from_rotvec(t[:, None] * rng.normal(scale=1.5, size=3)[None])
        pose[:, sl] = R.as_rotvec() if kind == "aa" else np.unwrap(R.as_euler(seq), axis=0) * signs
    rr = (
        Rotation.from_rotvec([0.1, 0.2, 0.3]) * Rotation.from_rotvec(t[:, None] * np.array([[0.0, 2.0, 0.5]]))
    ).as_rotvec()
    rt = np.array([0.1, 0.9, -0.2]) + t[:, None] * np.array([[0.5, 0.0, -0.3]])
    face = t[:, None] * np.array([[1.0, -2.0]])
    return [x.astype(np.float32) for x in (pose, rr, rt, face)]


def test_resample_60_to_30_is_every_other_frame_and_15_to_30_slerps_midpoints():
    from prep_fixtures import arm_rig

    rig = arm_rig()  # euler triplets and an axis-angle joint
    assert {k for k, *_ in _joint_layouts(rig)} == {"euler3", "aa"}
    m60 = _constant_velocity_motion(rig, 13, 60.0, seed=1)
    p, rr, rt, face, times = resample_motion(*m60, rig, 60.0, 30.0)
    assert len(p) == 7 and not times.alpha.any()
    for a, b in zip((p, rr, rt, face), m60):
        assert np.array_equal(a, b[::2])  # bit-exact

    gt30 = _constant_velocity_motion(rig, 9, 30.0, seed=2)
    m15 = [x[::2] for x in gt30]
    p, rr, rt, face, times = resample_motion(*m15, rig, 15.0, 30.0)
    assert len(p) == 9 and np.allclose(times.alpha[1::2], 0.5)
    for a, b in zip((p, rr, rt, face), gt30):
        np.testing.assert_allclose(a, b, atol=2e-5)
    for a, b in zip((p, rr, rt, face), m15):  # source frames copied exactly
        assert np.array_equal(a[::2], b)
    # naive per-parameter lerp of the euler angles would not hit the true midpoints
    lerp = 0.5 * (m15[0][:-1] + m15[0][1:])
    assert np.abs(lerp - gt30[0][1::2]).max() > 1e-3


# --------------------------------------------------------------------------- loading
def test_load_motion_from_capture_npz_and_bvh(tiny_capture, tmp_path):
    cap = load_capture(tiny_capture)
    rig = cap.rig
    m = load_driving_motion(tiny_capture, rig, cap.fps, split="test")
    assert m.pose.shape == (3, rig.pose_dim) and m.face.shape[0] == 3
    assert m.gt is not None and m.gt.frames == [9, 10, 11] and m.fps == cap.fps
    half = load_driving_motion(tiny_capture, rig, cap.fps / 2)  # 15 -> 7.5: every other frame, GT kept
    assert half.gt.frames == list(range(0, cap.num_frames, 2))
    assert np.array_equal(half.pose, cap.motion.pose[::2])
    double = load_driving_motion(tiny_capture, rig, cap.fps * 2, count=4)  # midpoints: no GT
    assert double.num_frames == 7 and double.gt is None and double.source_fps == cap.fps

    npz = tmp_path / "walk.npz"
    np.savez(
        npz, pose=cap.motion.pose, root_rotation=cap.motion.root_rotation, root_translation=cap.motion.root_translation
    )
    with pytest.raises(ValueError, match="frame rate unknown"):
        load_driving_motion(npz, rig, 15.0)
    (tmp_path / "walk.json").write_text(json.dumps({"fps": 30.0}))  # sidecar
    m = load_driving_motion(npz, rig, 15.0)
    assert m.num_frames == 6 and m.source_fps == 30.0 and m.face is None and m.gt is None
    assert load_driving_motion(npz, rig, 15.0, fps=15.0).num_frames == cap.num_frames

    if BVH.exists():
        b = load_driving_motion(BVH, rig, 15.0, start=1040, count=5)
        assert b.pose.shape == (5, rig.pose_dim) and np.isfinite(b.pose).all() and b.fps == 15.0

    bad = tmp_path / "bad.npz"
    np.savez(
        bad, pose=np.zeros((4, rig.pose_dim + 1)), root_rotation=np.zeros((4, 3)), root_translation=np.zeros((4, 3))
    )
    with pytest.raises(SchemaError, match="pose") as e:
        load_driving_motion(bad, rig, 15.0, fps=15.0)
    assert e.value.field == "pose" and str(bad) in str(e.value)
    rt = np.zeros((4, 3))
    rt[2, 1] = np.nan
    np.savez(bad, pose=np.zeros((4, rig.pose_dim)), root_rotation=np.zeros((4, 3)), root_translation=rt)
    with pytest.raises(SchemaError, match="frame 2") as e:
        load_driving_motion(bad, rig, 15.0, fps=15.0)
    assert e.value.field == "root_translation"


# --------------------------------------------------------------------------- driver
def test_streaming_equals_batch_and_render_afterwards(loaded, tiny_run, tiny_capture):
    from gsavatar.runs.views import render_views

    net, scene, tcfg, _ = loaded
    pred = small_predictor(net)
    motion = load_driving_motion(tiny_capture, scene.capture.rig, scene.capture.fps, split="test")
    cfg = DriveConfig(mode="reinit", reinit_every=2, image_scale=0.25)
    d = Driver(tiny_run, cfg, loaded=loaded, predictor=pred)
    frames = d.drive(motion)
    assert [f.t for f in frames] == [0, 1, 2] and list(frames[0].images) == ["full01"]

    # re-implementation: latents by the predictor's own rollout, rendered afterwards
    from gsavatar.drive.driver import texture_source

    tex = texture_source(motion, scene, None)
    enc = lambda t: net.latents(tex(t)[None], None)[0][0]  # noqa: E731
    f = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    ref = pred.rollout(
        f(motion.pose),
        f(motion.root_rotation),
        f(motion.root_translation),
        init_latents=enc(0),
        first_is_given=True,
        reinit_every=2,
        reinit_latents=enc,
    )
    got = torch.stack([fr.latents for fr in frames])
    assert torch.equal(got, ref)
    assert torch.equal(got[0], enc(0)) and not torch.equal(got[1], got[0])
    v = d.views[0]
    with torch.no_grad():
        for t, fr in enumerate(frames):
            x = motion_inputs(motion, t)
            batch = FrameBatch(
                x.pose[None], x.root_rotation[None], x.root_translation[None], x.face[None], latents=ref[t][None]
            )
            out = net(batch, sh_degree=d.sh_degree, correctives=True)
            col, _ = render_views(
                out.avatar, v.viewmat[None], v.K[None], v.width, v.height, torch.zeros(1, 3), d.sh_degree, tcfg.backend
            )
            torch.testing.assert_close(fr.images["full01"], col[0].clamp(0, 1).permute(1, 2, 0), rtol=0, atol=1e-6)

    # other modes, latents only: zero init and pose-conditioned init match the rollout too
    for mode, init in (("predictor", torch.zeros_like(ref[0])), ("pose_init", None)):
        p2 = small_predictor(net, trained_init=mode == "pose_init")
        d2 = Driver(tiny_run, DriveConfig(mode=mode), loaded=loaded, predictor=p2)
        d2.start(motion_inputs(motion, 0))
        lat = torch.stack([d2.step(motion_inputs(motion, t), render=False).latents for t in range(3)])
        assert torch.equal(lat, p2.rollout(f(motion.pose), f(motion.root_rotation), f(motion.root_translation), init))
    # pose only: the InitialLatentNet of each frame's pose, no state carried between frames
    p3 = small_predictor(net, trained_init=True)
    d3 = Driver(tiny_run, DriveConfig(mode="pose_regression"), loaded=loaded, predictor=p3)
    d3.start(motion_inputs(motion, 2))  # the start frame does not matter: nothing is carried
    lat = torch.stack([d3.step(motion_inputs(motion, t), render=False).latents for t in range(3)])
    ref_pose = torch.stack([p3.initial_latents(f(motion.pose)[t : t + 1])[0] for t in range(3)])
    assert torch.equal(lat, ref_pose) and not torch.equal(lat[0], lat[1])


def test_bvh_orbit_driving_and_ramp_up(loaded, tiny_run, tiny_capture, tmp_path):
    net, scene, _, _ = loaded
    pred = small_predictor(net, trained_init=True)
    if BVH.exists():
        m = load_driving_motion(BVH, scene.capture.rig, scene.capture.fps, start=1040, count=2)
        d = Driver(tiny_run, DriveConfig(cameras="orbit", orbit_views=1, orbit_size=24), loaded=loaded, predictor=pred)
        frames = d.drive(m)
        img = frames[1].images["orbit00"]
        assert img.shape == (24, 24, 3) and frames[1].alphas["orbit00"].max() > 0.5  # the avatar is in view
    motion = load_driving_motion(tiny_capture, scene.capture.rig, scene.capture.fps, count=4)
    with pytest.raises(ValueError, match="start"):
        Driver(tiny_run, DriveConfig(), loaded=loaded, predictor=pred).step(motion_inputs(motion, 0))
    from gsavatar.drive.driver import texture_source

    d = Driver(tiny_run, DriveConfig(image_scale=0.25), loaded=loaded, predictor=pred)
    res = measure_ramp_up(d, motion, texture_source(motion, scene, None), frames=3, with_images=False)
    assert set(res["modes"]) == {"predictor", "pose_init", "predictor_encoder_init", "encoder"}
    assert res["modes"]["predictor_encoder_init"]["latent_l1"][0] == 0.0
    assert all(v == 0.0 for v in res["modes"]["encoder"]["latent_l1"])
    js, png = write_ramp_up(res, tmp_path)
    import cv2

    assert json.loads(js.read_text())["frames"] == 3 and cv2.imread(str(png)) is not None


# --------------------------------------------------------------------------- latent sources
@pytest.fixture
def source_table():
    """Sources registered by a test are unregistered after it."""
    before = dict(LATENT_SOURCES)
    yield LATENT_SOURCES
    LATENT_SOURCES.clear()
    LATENT_SOURCES.update(before)


def test_adding_a_drive_mode_is_one_class(loaded, tiny_run, tiny_capture, source_table):
    # A new drive mode, defined here without touching gsavatar: the class statement registers it.
    class HoldFirst(LatentSource, mode="hold_first"):
        """The encoder's latents of frame 0, held for the whole sequence."""

        needs_texture = True

        def texture_needed_at(self, t: int) -> bool:
            return t == 0

        def init(self, x: FrameInputs) -> None:
            self.first = self.ctx.encode(x.texture)  # [A, L]

        def next(self, x: FrameInputs, t: int) -> torch.Tensor:
            return self.first

    assert source_table["hold_first"] is HoldFirst and HoldFirst.mode == "hold_first"
    net, scene, _, _ = loaded
    motion = load_driving_motion(tiny_capture, scene.capture.rig, scene.capture.fps, count=4)
    from gsavatar.drive.driver import texture_source

    tex, asked = texture_source(motion, scene, None), []
    d = Driver(tiny_run, DriveConfig(mode="hold_first", image_scale=0.25), loaded=loaded)  # needs no predictor
    assert d.predictor is None and d.needs_textures
    frames = d.drive(motion, lambda t: asked.append(t) or tex(t))
    assert asked == [0]  # the texture of frame 0 only
    enc = d.with_mode("encoder").drive(motion)  # the encoder's latents every frame, same cameras
    assert all(torch.equal(f.latents, enc[0].latents) for f in frames)
    assert torch.equal(frames[0].images["full01"], enc[0].images["full01"])
    assert not torch.equal(frames[3].latents, enc[3].latents)
    # ... and the ramp-up study measures it like the built-in modes
    res = measure_ramp_up(d, motion, tex, frames=2, modes=("hold_first", "encoder"), with_images=False)
    assert res["modes"]["hold_first"]["latent_l1"][0] == 0.0 and res["modes"]["hold_first"]["latent_l1"][1] > 0

    with pytest.raises(ValueError, match="already registered"):
        type("Again", (LatentSource,), {}, mode="hold_first")


def test_drive_modes_come_from_one_table(loaded, tiny_run):
    import typing

    from gsavatar.drive.cli import DriveArgs

    modes = ("predictor", "pose_init", "predictor_encoder_init", "reinit", "train_mean", "pose_regression", "encoder")
    assert tuple(LATENT_SOURCES) == modes and typing.get_args(DriveMode) == modes
    assert typing.get_type_hints(DriveArgs)["drive"] is DriveConfig  # the CLI holds the config, no copy
    assert typing.get_type_hints(DriveConfig)["mode"] == DriveMode  # the CLI's --mode choices
    args = tyro.cli(DriveArgs, args=["--run", "r", "--motion", "m", "--mode", "encoder", "--image-scale", "0.5"])
    assert args.config() == DriveConfig(mode="encoder", image_scale=0.5)
    assert ramp_up_modes() == ("predictor", "pose_init", "predictor_encoder_init", "encoder")
    with pytest.raises(ValueError, match="mode must be one of predictor/pose_init/"):
        DriveConfig(mode="nope")
    needs = {m: (c.needs_texture, c.needs_predictor) for m, c in LATENT_SOURCES.items()}
    assert needs == {
        "predictor": (False, True),
        "pose_init": (False, True),
        "predictor_encoder_init": (True, True),
        "reinit": (True, True),
        "train_mean": (False, True),
        "pose_regression": (False, True),
        "encoder": (True, False),
    }
    pred = small_predictor(loaded.net)
    d = Driver(tiny_run, DriveConfig(mode="reinit", reinit_every=3), loaded=loaded, predictor=pred)
    assert [d.texture_needed_at(t) for t in range(7)] == [True, False, False, True, False, False, True]
    assert [d.with_mode("predictor_encoder_init").texture_needed_at(t) for t in range(3)] == [True, False, False]
    assert not d.with_mode("predictor").needs_textures
    m = d.with_mode("train_mean")  # the predictor's training-mean latent, every frame, no texture
    m.start(FrameInputs(np.zeros(d.pose_dim), np.zeros(3), np.zeros(3)))
    assert torch.equal(
        m.step(FrameInputs(np.zeros(d.pose_dim), np.zeros(3), np.zeros(3)), render=False).latents, pred.latent_mean
    )
    e = d.with_mode("encoder")  # a plain constructor call sharing the run and predictor
    assert e.net is d.net and e.predictor is d.predictor and e.config.reinit_every == 3 and e.t == -1
    for mode in ("pose_init", "pose_regression"):
        with pytest.raises(ValueError, match="trained InitialLatentNet"):
            d.with_mode(mode)  # the small predictor's initial net is untrained
    no_pred = Driver(tiny_run, DriveConfig(mode="encoder"), loaded=loaded, predictor=None)
    with pytest.raises(ValueError, match="needs a trained appearance predictor"):
        no_pred.with_mode("predictor")

    x = no_pred.check_inputs(FrameInputs(np.zeros(d.pose_dim), np.zeros(3), np.zeros(3)))  # the public input check
    assert x.pose.dtype == torch.float32 and (x.face is None) == (d.face_dim == 0)
    with pytest.raises(ValueError, match=r"root_rotation must be \[3\]"):
        no_pred.check_inputs(FrameInputs(np.zeros(d.pose_dim), np.zeros(4), np.zeros(3)))


def test_sequence_metrics_zero_error_when_render_is_the_ground_truth():
    g = torch.rand(3, 16, 16, 3)
    mask = torch.zeros(16, 16)
    mask[4:12, 4:12] = 1
    acc = SequenceMetrics()
    for t in range(3):
        acc.add(t, "c", g[t], mask, g[t], mask)
    s = acc.summary()
    assert s["mean"]["temporal_error"] == 0.0 and s["mean"]["render_change"] > 0 and s["mean"]["psnr"] == float("inf")
    acc2 = SequenceMetrics()
    for t in range(3):
        acc2.add(t, "c", g[0], mask, g[t], mask)  # frozen render of a changing scene
    assert acc2.summary()["mean"]["temporal_error"] > 0.1


# --------------------------------------------------------------------------- CLI
def test_cli_encoder_mode_writes_video_latents_metrics_and_figure(tiny_run, tiny_capture, tmp_path):
    import cv2
    import imageio.v2 as imageio

    out = tmp_path / "drive"
    rc = main(
        [
            "--run",
            str(tiny_run),
            "--motion",
            str(tiny_capture),
            "--split",
            "test",
            "--mode",
            "encoder",
            "--image-scale",
            "0.5",
            "--lpips",
            "off",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    r = imageio.get_reader(out / "drive.mp4")
    assert r.count_frames() == 3 and r.get_data(0).shape[:2] == (64, 64)
    r.close()
    z = np.load(out / "latents.npz")
    assert z["latents"].shape[0] == 3 and z["pose"].shape[0] == 3
    assert sorted(p.name for p in (out / "frames" / "full01").iterdir()) == [f"{t:06d}.png" for t in range(3)]
    met = json.loads((out / "metrics.json").read_text())
    assert met["gt_frames"] == [9, 10, 11]
    for k in ("psnr", "psnr_fg", "ssim", "temporal_error", "render_change"):
        assert np.isfinite(met["mean"][k]), k
    assert cv2.imread(str(out / met["stability_figure"])).shape[0] >= 2 * 64  # render + GT rows
    assert not list(out.glob(".*"))  # no temp files left behind


def test_cli_bad_inputs_exit_2_naming_file_and_field(tiny_run, tiny_capture, tmp_path, capsys):
    P = load_capture(tiny_capture).rig.pose_dim
    common = ["--out", str(tmp_path / "o"), "--lpips", "off", "--mode", "encoder"]
    assert main(["--run", str(tmp_path / "nope"), "--motion", str(tiny_capture), *common]) == 2
    assert "config.json" in capsys.readouterr().err

    wide = tmp_path / "wide.npz"
    np.savez(
        wide, pose=np.zeros((3, P + 2)), root_rotation=np.zeros((3, 3)), root_translation=np.zeros((3, 3)), fps=15.0
    )
    assert main(["--run", str(tiny_run), "--motion", str(wide), *common]) == 2
    err = capsys.readouterr().err
    assert "wide.npz: pose" in err and f"[T, {P}]" in err

    nan = tmp_path / "nan.npz"
    rr = np.zeros((3, 3))
    rr[1, 0] = np.nan
    np.savez(nan, pose=np.zeros((3, P)), root_rotation=rr, root_translation=np.zeros((3, 3)), fps=15.0)
    assert main(["--run", str(tiny_run), "--motion", str(nan), *common]) == 2
    err = capsys.readouterr().err
    assert "nan.npz: root_rotation" in err and "NaN" in err

    assert (
        main(["--run", str(tiny_run), "--motion", str(nan), "--out", str(tmp_path / "o"), "--reinit-every", "0"]) == 2
    )
    assert "reinit_every" in capsys.readouterr().err
    good = tmp_path / "good.npz"
    np.savez(good, pose=np.zeros((3, P)), root_rotation=np.zeros((3, 3)), root_translation=np.zeros((3, 3)), fps=15.0)
    assert main(["--run", str(tiny_run), "--motion", str(good), *common]) == 2  # encoder mode without textures
    assert "textures" in capsys.readouterr().err
    common[-1] = "predictor"  # this run has no trained predictor
    assert main(["--run", str(tiny_run), "--motion", str(good), *common]) == 2
    assert "predictor" in capsys.readouterr().err
    assert not (tmp_path / "o" / "drive.mp4").exists()


def test_cli_predictor_mode_loads_the_runs_trained_predictor(tiny_run, tiny_capture, tmp_path):
    import shutil

    import imageio.v2 as imageio

    from gsavatar.train.predictor import PredictorTrainConfig, train_predictor

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)  # the module's run stays without a predictor
    model = PredictorConfig(history=4, width=16, heads=2, ff=32, token_hidden=8, initial_hidden=16)
    train_predictor(
        run, PredictorTrainConfig(steps=1, batch_size=1, window=2, model=model), device="cpu", evaluate=False
    )
    assert (run / "predictor" / "latest.pt").exists()
    out = tmp_path / "drive"
    rc = main(
        [
            "--run",
            str(run),
            "--motion",
            str(tiny_capture),
            "--mode",
            "predictor_encoder_init",
            "--count",
            "2",
            "--capture-cameras",
            "full01",
            "--image-scale",
            "0.25",
            "--lpips",
            "off",
            "--no-write-frames",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    info = json.loads((out / "drive.json").read_text())
    assert info["mode"] == "predictor_encoder_init" and info["frames"] == 2 and info["ground_truth"]
    r = imageio.get_reader(out / "drive.mp4")
    assert r.count_frames() == 2
    r.close()
    assert not (out / "frames").exists()


def test_compare_figure_renders_each_latent_source(loaded, tiny_run, tiny_capture, tmp_path):
    import cv2

    from gsavatar.drive.compare import CompareArgs, compare

    scene = loaded.scene
    d = Driver(
        tiny_run,
        DriveConfig(mode="encoder", capture_cameras=("full01",), image_scale=0.5),
        loaded=loaded,
        predictor=None,
    )
    motion = load_driving_motion(tiny_capture, scene.capture.rig, d.fps, split="test")
    frames = d.drive(motion)
    (tmp_path / "enc").mkdir()
    np.savez(tmp_path / "enc" / "latents.npz", latents=torch.stack([f.latents for f in frames]).numpy())
    out = tmp_path / "cmp.png"
    info = compare(CompareArgs(run=tiny_run, out=out, drive=[f"encoder={tmp_path / 'enc'}"], frame=1, image_scale=0.5))
    assert list(info["psnr_fg"]) == ["encoder", "mean latent"] and info["capture_frame"] == motion.gt.frames[1]
    assert cv2.imread(str(out)) is not None and json.loads(out.with_suffix(".json").read_text())["camera"] == "full01"
    from gsavatar.drive.metrics import load_ground_truth
    from gsavatar.metrics.image import psnr

    gt, mask = load_ground_truth(scene.capture, motion.gt.frames[1], ["full01"], 0.5, torch.zeros(3))["full01"]
    m = (mask > 0.5)[None, None].expand(1, 3, *mask.shape)
    want = float(psnr(frames[1].images["full01"].permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], mask=m)[0])
    if not torch.cuda.is_available():  # compare loads the run on CUDA when it can: another rasterizer there
        assert info["psnr_fg"]["encoder"] == pytest.approx(want, abs=1e-6)  # the driver's render of those latents
    assert np.isfinite(info["psnr_fg"]["encoder"])


def test_latent_plot_shows_encoder_and_predictor_latents(tiny_run, tmp_path):
    """The demo's appearance-over-time figure: PC1 of encoder / predictor / mean latents; refuses a user's file."""
    from gsavatar.drive.latent_plot import LatentPlotArgs, write_latent_plot
    from gsavatar.train.cli import main as train_main
    from gsavatar.utils.errors import SchemaError

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    assert (
        train_main(
            [
                "predictor",
                "--run",
                str(run),
                "--steps",
                "2",
                "--window",
                "2",
                "--batch-size",
                "2",
                "--model.history",
                "3",
                "--model.width",
                "16",
                "--model.heads",
                "2",
                "--model.ff",
                "32",
                "--model.latent-pca",
                "global",
                "--model.latent-pca-components",
                "4",
            ]
        )
        == 0
    )
    out = tmp_path / "fig" / "states.png"
    res = write_latent_plot(LatentPlotArgs(run=run, out=out))
    assert out.exists() and out.with_suffix(".json").exists()
    assert set(res["pc1"]) == {"encoder", "predictor (zero init)", "predictor (encoder init)", "training mean"}
    T = len(res["frames"])
    assert T >= 2 and all(len(v) == T for v in res["pc1"].values())
    assert res["sources"]["encoder"]["l1_to_encoder"] == 0.0
    # encoder init: its first frame is the encoder's own latent
    assert res["pc1"]["predictor (encoder init)"][0] == pytest.approx(res["pc1"]["encoder"][0], abs=1e-4)
    write_latent_plot(LatentPlotArgs(run=run, out=out))  # its own figure: replaced
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"a user's picture")
    with pytest.raises(SchemaError, match="not a gsavatar figure"):
        write_latent_plot(LatentPlotArgs(run=run, out=mine))
    assert mine.read_bytes() == b"a user's picture"
