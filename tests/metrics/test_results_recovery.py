"""results.json's predictor recovery (benchmarks/results_table.py) on hand-made PSNRs, including a capture whose
encoder latents buy nothing on its test frames."""

from __future__ import annotations

import pytest
from benchmark_modules import load_benchmark


@pytest.fixture(scope="module")
def results_table():
    return load_benchmark("results_table")


def test_recovery_is_the_ratio_of_gains_over_the_mean_latent(results_table):
    r = results_table.recovery_fields(20.0, 22.0, 21.5, no_history=20.5, pose_only=19.0)
    assert r["predictor_recovery"] == pytest.approx(0.75)
    assert r["predictor_recovery_no_history"] == pytest.approx(0.25)
    assert r["predictor_recovery_pose_only"] == pytest.approx(-0.5)
    assert r["mean_latent_psnr_fg"] == 20.0
    assert "predictor_recovery_undefined" not in r


@pytest.mark.parametrize("encoder", [19.35, 20.0, 20.05])
def test_recovery_is_null_with_its_reason_when_the_encoder_gains_nothing(results_table, encoder):
    """An encoder at or below the mean latent (measured: `second` rendered without the light, -0.61 dB) would give a
    ratio of the wrong sign or noise over noise; the field stays present so a checking script finds it."""
    r = results_table.recovery_fields(20.0, encoder, 20.4, no_history=20.1)
    assert r["predictor_recovery"] is None
    assert "no gain to divide by" in r["predictor_recovery_undefined"]
    assert "+0.40 dB" in r["predictor_recovery_undefined"]
    assert r["predictor_recovery_no_history"] is None  # its row exists: undefined, not missing
    assert "predictor_recovery_pose_only" not in r  # no such row
    assert r["mean_latent_psnr_fg"] == 20.0


def test_recovery_is_null_naming_a_missing_row(results_table):
    r = results_table.recovery_fields(None, 22.0, 21.0)
    assert r["predictor_recovery"] is None and "training-mean latent" in r["predictor_recovery_undefined"]
    r = results_table.recovery_fields(20.0, 22.0, None)
    assert r["predictor_recovery"] is None and "zero init" in r["predictor_recovery_undefined"]
