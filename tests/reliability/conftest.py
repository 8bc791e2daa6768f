"""Fixtures of the reliability suite, built once per session on top of ``tiny_dataset``."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def pose_only_run(tiny_dataset, tmp_path_factory) -> Path:
    """A 1-step MMLPs-dagger run: no appearance latents, so ``avatar-drive`` renders any motion
    (npz, BVH, capture) in any mode without a trained predictor or textures."""
    from gsavatar.train.cli import main

    run = tmp_path_factory.mktemp("rel_run") / "run"
    assert (
        main(
            [
                "avatar",
                "--dataset",
                str(tiny_dataset),
                "--out",
                str(run),
                "--preset",
                "tiny",
                "--steps",
                "1",
                "--variant",
                "mmlps_dagger",
                "--lpips",
                "off",
                "--image-scale",
                "0.5",
                "--no-evaluate",
                "--deterministic",
            ]
        )
        == 0
    )
    return run


@pytest.fixture(scope="session")
def drive_output(pose_only_run, tiny_capture, tmp_path_factory) -> Path:
    """Outputs of a successful ``avatar-drive`` (frames, video, latents, metrics): the 'already written'
    results. White background, so a later drive (black) that overwrote a frame would change its bytes."""
    from gsavatar.drive.cli import main

    out = tmp_path_factory.mktemp("rel_drive") / "out"
    assert (
        main(
            [
                "--run",
                str(pose_only_run),
                "--motion",
                str(tiny_capture),
                "--out",
                str(out),
                "--count",
                "2",
                "--lpips",
                "off",
                "--image-scale",
                "0.25",
                "--background",
                "1",
                "1",
                "1",
            ]
        )
        == 0
    )
    return out
