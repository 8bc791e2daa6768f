"""avatar-train end to end on the tiny synthetic capture: train, resume (incl. kill -9), DDP, baseline, export."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from gsavatar.train.cli import main

REPO = Path(__file__).resolve().parents[2]
FAST = [
    "--preset",
    "tiny",
    "--lpips",
    "off",
    "--image-scale",
    "0.5",
    "--log-every",
    "1",
    "--no-evaluate",
    "--deterministic",
]


def _curve(run: Path) -> dict[int, float]:
    out = {}
    for line in (run / "metrics.jsonl").read_text().splitlines():
        r = json.loads(line)
        assert r["step"] not in out, f"step {r['step']} logged twice"  # resumes trim the log
        out[r["step"]] = r["total"]
    return out


def _params(run: Path) -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["modules"]["net"]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}


def test_train_resume_gives_the_same_curve(tiny_dataset, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    args = ["avatar", "--dataset", str(tiny_dataset), *FAST, "--steps", "6", "--checkpoint-every", "2"]
    assert main([*args, "--out", str(a)]) == 0
    assert main([*args, "--out", str(b), "--max-steps-this-run", "3"]) == 0
    assert max(_curve(b)) == 3
    assert main([*args, "--out", str(b)]) == 0  # resumes at step 3
    ca, cb = _curve(a), _curve(b)
    assert sorted(ca) == sorted(cb) == list(range(1, 7))
    assert ca == cb  # deterministic mode: bit-identical
    pa, pb = _params(a), _params(b)
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k


def test_kill_9_mid_run_then_resume(tiny_dataset, tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    args = ["avatar", "--dataset", str(tiny_dataset), *FAST, "--steps", "8", "--checkpoint-every", "2"]
    assert main([*args, "--out", str(ref)]) == 0
    p = subprocess.Popen(
        [sys.executable, "-m", "gsavatar.train.cli", *args, "--out", str(run)],
        env=_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 240
    while time.time() < deadline and p.poll() is None:
        m = run / "metrics.jsonl"
        if m.exists() and max(_curve(run), default=0) >= 3:
            break
        time.sleep(0.2)
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert (run / "checkpoints" / "latest.pt").exists()
    assert main([*args, "--out", str(run)]) == 0
    assert _curve(ref) == _curve(run)
    pr, pu = _params(ref), _params(run)
    assert all(torch.equal(pr[k], pu[k]) for k in pr)


def test_two_gloo_ranks_equal_one_rank(tiny_dataset, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    args = [
        "avatar",
        "--dataset",
        str(tiny_dataset),
        *FAST,
        "--steps",
        "3",
        "--batch-size",
        "2",
        "--checkpoint-every",
        "3",
    ]
    assert main([*args, "--out", str(one)]) == 0
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            "2",
            "-m",
            "gsavatar.train.cli",
            *args,
            "--out",
            str(two),
        ],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    c1, c2 = _curve(one), _curve(two)
    assert sorted(c1) == sorted(c2) == [1, 2, 3]
    # The all-reduce sums gradients in another order than one process does; AdamW (eps=1e-15)
    # turns those last-bit differences into up-to-lr-sized steps for parameters whose gradient
    # is ~0, so compare the global-batch loss curve (logged as the all-reduced mean).
    for s in c1:
        assert c2[s] == pytest.approx(c1[s], rel=1e-3), s
    # and the parameters that carry real gradient (the per-Gaussian colours) agree closely
    p1, p2 = _params(one), _params(two)
    # (all but the few Gaussians that are nearly invisible, whose Adam steps are sign noise)
    a, b = p1["avatar.sh0_bias"], p2["avatar.sh0_bias"]
    close = torch.isclose(a, b, rtol=1e-3, atol=1e-4).float().mean()
    assert close > 0.99, float(close)


@pytest.mark.parametrize("variant,model_variant", [("mmlps_dagger", "mmlps"), ("nrfgca_dagger", "conv_uv")])
def test_baseline_flag_eval_and_export(tiny_dataset, tmp_path, capsys, variant, model_variant):
    run = tmp_path / variant
    assert (
        main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
                *FAST,
                "--steps",
                "2",
                "--correctives-step",
                "0",
                "--variant",
                variant,
                "--out",
                str(run),
            ]
        )
        == 0
    )
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["model"]["variant"] == model_variant and cfg["model"]["use_latent"] is False
    assert main(["eval", "--run", str(run), "--eval-frames", "1"]) == 0
    res = json.loads((run / "eval" / "metrics.json").read_text())
    assert res["variant"] == variant and 5 < res["train_frames_heldout_cams"]["psnr"] < 60
    assert "latent_gain_db" not in res  # no latents in the baselines
    ply = tmp_path / "f0.ply"
    assert main(["export", "--run", str(run), "--frame", "0", "--out", str(ply)]) == 0
    from gsavatar.models.ply import read_ply

    g = read_ply(ply)
    assert g.means.shape[0] > 1000 and torch.isfinite(torch.as_tensor(g.means)).all()


def test_checkpoint_of_another_config_is_refused(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "r"
    base = ["avatar", "--dataset", str(tiny_dataset), *FAST, "--out", str(run), "--steps", "1"]
    assert main(base) == 0
    assert main([*base[:-2], "--steps", "2", "--variant", "mmlps_dagger"]) == 2
    err = capsys.readouterr().err
    assert "latest.pt" in err and "config.model" in err


def test_eval_reports_the_latent_gain_and_it_is_zero_when_latents_are_cut(tiny_dataset, tmp_path):
    from gsavatar.runs.load import load_run
    from gsavatar.train.runs import evaluate_run

    run = tmp_path / "ours"
    assert (
        main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
                *FAST,
                "--steps",
                "2",
                "--correctives-step",
                "0",
                "--out",
                str(run),
            ]
        )
        == 0
    )
    assert main(["eval", "--run", str(run), "--eval-frames", "1"]) == 0
    res = json.loads((run / "eval" / "metrics.json").read_text())
    gain = res["test_frames_heldout_cams"]["psnr_fg"] - res["test_frames_heldout_cams_mean_latent"]["psnr_fg"]
    assert res["latent_gain_db"] == pytest.approx(gain)
    loaded = load_run(run, "cpu")
    net = loaded.net
    L = net.avatar.latent_in
    with torch.no_grad():
        net.avatar.pose_head.mlp.weights[0][:, -L:] = 0  # the anchor MLPs no longer see the latent
        if net.avatar.sh0_latent_basis is not None:  # nor does the latent colour map (CPU recipe)
            net.avatar.sh0_latent_basis.zero_()
    res = evaluate_run(tmp_path / "cut", 1, loaded=loaded)
    assert res["latent_gain_db"] == pytest.approx(0.0, abs=1e-9)


def test_encoder_is_untouched_until_the_correctives_switch_on(tiny_dataset, tmp_path):
    # Before the correctives the latent has no effect; a KL term alone would pull the posterior to the prior.
    from gsavatar.models.net import build_net
    from gsavatar.runs.config import model_config
    from gsavatar.runs.load import load_run

    run = tmp_path / "r"
    assert (
        main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
                *FAST,
                "--steps",
                "3",
                "--correctives-step",
                "100",
                "--out",
                str(run),
            ]
        )
        == 0
    )
    net, scene, cfg, _ = load_run(run, "cpu")
    init = build_net(scene, model_config(cfg), cfg.seed)
    for (k, a), b in zip(net.encoder.state_dict().items(), init.encoder.state_dict().values()):
        assert torch.equal(a, b), k
    assert any(not torch.equal(a, b) for a, b in zip(net.avatar.parameters(), init.avatar.parameters()))


def test_oracle_run_reads_ground_truth_albedo_and_eval_reports_frame_dependence(tiny_dataset, tmp_path):
    from gsavatar.data_schema.prepared import resize_face_mask
    from gsavatar.data_schema.prepared import load_scene
    from gsavatar.train.data import ViewDataset
    from gsavatar.utils.io import read_image

    run = tmp_path / "oracle"
    assert (
        main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
                *FAST,
                "--steps",
                "3",
                "--correctives-step",
                "0",
                "--texture-source",
                "gt",
                "--out",
                str(run),
            ]
        )
        == 0
    )
    assert json.loads((run / "config.json").read_text())["train"]["texture_source"] == "gt"
    assert main(["eval", "--run", str(run), "--eval-frames", "2"]) == 0
    res = json.loads((run / "eval" / "metrics.json").read_text())
    fd = res["frame_dependence"]
    assert fd["std_gt"] > 0 and fd["ratio"] >= 0 and fd["frames"] >= 2
    assert np.isfinite(res["latent_gain_db"])
    # the encoder's input is the ground-truth albedo (face blanked like the projected textures), not the projection
    scene = load_scene(tiny_dataset)
    gt_data = ViewDataset(scene, "train", texture_source="gt")
    f = gt_data.frames[0]
    tex = gt_data.frame_inputs(f)["texture"].permute(1, 2, 0).numpy()
    ref = read_image(scene.capture.root / "gt" / "textures" / f"{f:08d}.png")
    S = scene.tex_size
    ref = cv2.resize(ref, (S, S), interpolation=cv2.INTER_AREA)  # GT albedo at the prepared texture size
    face = resize_face_mask(scene.capture.template.face_uv_mask, S)
    np.testing.assert_allclose(tex[~face], ref[~face], atol=1e-3)  # float16 cache
    assert (tex[face] == 0).all()
    assert not np.allclose(tex, ViewDataset(scene, "train").frame_inputs(f)["texture"].permute(1, 2, 0).numpy())


def test_resume_identifies_the_dataset_by_content_not_path(tiny_dataset, tmp_path, capsys):
    import shutil

    run = tmp_path / "r"
    args = [*FAST, "--steps", "4", "--checkpoint-every", "2"]
    assert main(["avatar", "--dataset", str(tiny_dataset), *args, "--max-steps-this-run", "2", "--out", str(run)]) == 0
    link = tmp_path / "same_dataset"
    link.symlink_to(tiny_dataset, target_is_directory=True)
    assert main(["avatar", "--dataset", str(link), *args, "--max-steps-this-run", "1", "--out", str(run)]) == 0
    other = tmp_path / "other"
    shutil.copytree(tiny_dataset, other, symlinks=True)
    meta = json.loads((other / "dataset.json").read_text())
    name = sorted(meta["stages"])[0]
    meta["stages"][name]["config"] = {**(meta["stages"][name]["config"] or {}), "changed": 1}  # another preparation
    (other / "dataset.json").write_text(json.dumps(meta))
    before = (run / "checkpoints" / "latest.pt").read_bytes()
    assert main(["avatar", "--dataset", str(other), *args, "--out", str(run)]) == 2
    assert "dataset_id" in capsys.readouterr().err
    assert (run / "checkpoints" / "latest.pt").read_bytes() == before


def test_checkpoint_of_an_older_model_config_resumes(tmp_path):
    """A model-config field added later (with a default that keeps the old behaviour) does not orphan a run
    whose checkpoint predates it; a real difference is still refused."""
    import dataclasses

    import torch

    from gsavatar.models.config import ModelConfig, model_preset
    from gsavatar.runs.checkpoint import load_checkpoint, save_checkpoint
    from gsavatar.utils.errors import SchemaError
    from gsavatar.utils.jsonio import dataclass_defaults

    now = json.loads(json.dumps(dataclasses.asdict(model_preset("tiny")), default=list))
    old = {k: v for k, v in now.items() if k not in ("anchor_sh0", "mlp_init")}  # written before those fields
    ckpt = tmp_path / "latest.pt"
    save_checkpoint(ckpt, step=3, config={"model": old}, modules={"m": torch.nn.Linear(1, 1)}, optimizer=None)
    state = load_checkpoint(ckpt, {"model": now}, ("model",), defaults={"model": dataclass_defaults(ModelConfig)})
    assert state["step"] == 3
    # the run's own config.json may predate a field too (load_run compares it with a newer checkpoint)
    save_checkpoint(ckpt, step=4, config={"model": now}, modules={"m": torch.nn.Linear(1, 1)}, optimizer=None)
    state = load_checkpoint(ckpt, {"model": old}, ("model",), defaults={"model": dataclass_defaults(ModelConfig)})
    assert state["step"] == 4
    with pytest.raises(SchemaError, match="config.model"):  # without defaults: the old behaviour
        load_checkpoint(ckpt, {"model": old}, ("model",))
    save_checkpoint(ckpt, step=3, config={"model": old}, modules={"m": torch.nn.Linear(1, 1)}, optimizer=None)
    with pytest.raises(SchemaError, match="config.model"):  # a field that really differs
        load_checkpoint(
            ckpt,
            {"model": {**now, "anchor_sh0": True}},
            ("model",),
            defaults={"model": dataclass_defaults(ModelConfig)},
        )


def test_default_cpu_training_and_driving_take_the_compiled_paths(tiny_dataset, tmp_path):
    """The fast kernels (models/kernels.py) decline silently to their torch twins when a precondition fails;
    the path each took is recorded. With the default CPU configuration (no --deterministic) training and driving
    must run compiled: timing.json lists the training's kernels, the drive's are read in process."""
    from gsavatar.drive.cli import main as drive
    from gsavatar.models.kernels import numba, path_report, reset_paths

    if numba is None:
        pytest.skip("numba missing: the torch paths are the only ones")
    run = tmp_path / "run"
    reset_paths()
    args = ["avatar", "--dataset", str(tiny_dataset), "--preset", "tiny", "--lpips", "off", "--image-scale", "0.5"]
    assert main([*args, "--steps", "2", "--no-evaluate", "--out", str(run)]) == 0
    timing = json.loads((run / "timing.json").read_text())
    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent)
    if head.returncode == 0:  # the run names the commit that trained it (the results table checks it)
        assert timing["code"]["commit"] == head.stdout.strip() and timing["commits"] == [head.stdout.strip()]
    paths = timing["kernel_paths"]
    assert {"polar_rotation_fast", "sparse_interpolate_fast"} <= set(paths) or {
        "posed_quaternion_fast",
        "sparse_interpolate_fast",
    } <= set(paths), paths
    inference_only = {"pose_lbs_fast", "interpolated_deltas_fast"}  # by design: no backward, they decline in training
    for name, p in paths.items():
        if name in inference_only:
            assert p["compiled"] == 0 and "requires_grad" in p["why_torch"], (name, p)
        else:
            assert p["torch"] == 0 and p["compiled"] > 0, (name, p)
    reset_paths()
    out = tmp_path / "drive"
    assert (
        drive(
            [
                "--run",
                str(run),
                "--motion",
                str(json.loads((tiny_dataset / "dataset.json").read_text())["capture"]),
                "--count",
                "2",
                "--mode",
                "encoder",
                "--out",
                str(out),
                "--image-scale",
                "0.5",
            ]
        )
        == 0
    )
    paths = path_report()
    assert "pose_lbs_fast" in paths and "interpolated_deltas_fast" in paths, paths
    for name, p in paths.items():
        assert p["torch"] == 0 and p["compiled"] > 0, (name, p)
