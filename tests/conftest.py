import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import os

import pytest

REPO = Path(__file__).resolve().parents[1]


def anny_cache_dir() -> Path:
    return Path(os.environ.get("ANNY_CACHE_DIR", REPO / ".cache" / "anny"))


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    """The synthetic ``tiny`` capture (real anny body + CMU mocap), built once per session."""
    pytest.importorskip("anny")
    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset

    out = tmp_path_factory.mktemp("tiny") / "capture"
    make_capture(preset("tiny", seed=0), out, anny_cache_dir(), progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_dataset(tiny_capture, tmp_path_factory) -> Path:
    """``avatar-prep all`` on the tiny capture (128^2 textures, no figures)."""
    from gsavatar.prep.cli import main

    ds = tmp_path_factory.mktemp("tinyds") / "dataset"
    rc = main(
        [
            "all",
            "--capture",
            str(tiny_capture),
            "--out",
            str(ds),
            "--workers",
            "1",
            "--project.tex-size",
            "128",
            "--no-figures",
        ]
    )
    assert rc == 0
    return ds
