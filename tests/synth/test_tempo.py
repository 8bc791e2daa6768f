"""A motion played at a varying tempo (SynthConfig.tempo_variation): the time map against a naive interpolation,
the tempo curve's statistics, and what it is for: a spring's state on a cyclic motion stops being a function of
the pose while the pose history still tells it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import anny_cache_dir

from gsavatar.motion.resample import resample_motion, resample_motion_at, resample_times, times_at
from gsavatar.synth.presets import PRESETS, preset

BVH = PRESETS["small"].bvh_path


def test_tempo_curve_statistics_and_seed():
    from gsavatar.synth.make import tempo_curve

    cfg = preset("small")
    r = tempo_curve(cfg)
    assert r.shape == (cfg.num_frames,) and (r > 0).all()
    # log-rate: zero mean, standard deviation exactly tempo_variation (the noise is standardised)
    assert abs(np.log(r).mean()) < 1e-9 and np.log(r).std() == pytest.approx(cfg.tempo_variation, rel=1e-9)
    # smooth over tempo_smoothing_s (30 frames): neighbouring frames' log-rates are almost perfectly correlated
    z = np.log(r)
    assert np.corrcoef(z[:-1], z[1:])[0, 1] > 0.99
    np.testing.assert_array_equal(r, tempo_curve(cfg))  # deterministic
    assert not np.allclose(r, tempo_curve(dataclasses.replace(cfg, seed=cfg.seed + 1)))
    np.testing.assert_array_equal(tempo_curve(dataclasses.replace(cfg, tempo_variation=0.0)), 1.0)
    with pytest.raises(ValueError, match="tempo_variation"):
        tempo_curve(dataclasses.replace(cfg, tempo_variation=-0.1))
    with pytest.raises(ValueError, match="tempo_smoothing_s"):
        tempo_curve(dataclasses.replace(cfg, tempo_smoothing_s=0.0))


def test_times_at_matches_resample_times_and_interpolates_positions():
    t = resample_times(41, 120.0, 30.0)
    u = times_at(np.arange(11) * 4.0, 41)
    for a, b in zip(t, u):
        np.testing.assert_array_equal(a, b)
    w = times_at(np.array([0.0, 2.25, 39.5, 40.0]), 41)
    np.testing.assert_array_equal(w.i0, [0, 2, 39, 40])
    np.testing.assert_allclose(w.alpha, [0.0, 0.25, 0.5, 0.0])
    with pytest.raises(ValueError, match="within"):
        times_at(np.array([0.0, 40.5]), 41)
    with pytest.raises(ValueError, match="finite"):
        times_at(np.array([np.nan]), 41)


@pytest.fixture(scope="module")
def rig_and_source():
    pytest.importorskip("anny")
    from gsavatar.motion.retarget import motion_from_bvh_file
    from gsavatar.synth.body import build_anny_body

    _, rig = build_anny_body(anny_cache_dir(), decimate_to=3000, seed=0)
    return rig, motion_from_bvh_file(BVH, rig, fps_out=None, start=120, count=400)


def test_resample_motion_at_uniform_times_is_resample_motion(rig_and_source):
    rig, m = rig_and_source
    a = resample_motion(m.pose, m.root_rotation, m.root_translation, None, rig, 120.0, 30.0)
    b = resample_motion_at(m.pose, m.root_rotation, m.root_translation, None, rig, a[4])
    for x, y in zip(a[:3], b[:3]):
        np.testing.assert_array_equal(x, y)


def test_load_motion_plays_the_source_at_the_tempo_curve(rig_and_source):
    """Output frame k is the source at position sum_{j<k} rate_j * (120 / 30) (naive oracle: linear interpolation
    of the root translation, which the resampler interpolates linearly), and a segment too short for the tempo is
    refused naming the tempo."""
    from gsavatar.motion.retarget import motion_from_bvh_file
    from gsavatar.synth.make import load_motion, tempo_curve

    rig, _ = rig_and_source
    cfg = dataclasses.replace(preset("tiny"), num_frames=60, fps=30.0, bvh_start=300, tempo_variation=0.4)
    cfg = dataclasses.replace(cfg, root_xz="keep")
    got = load_motion(cfg, rig)
    src = motion_from_bvh_file(BVH, rig, fps_out=None, start=300)
    pos = np.concatenate([[0.0], np.cumsum(tempo_curve(cfg)[:-1])]) * 4.0
    i0 = np.floor(pos).astype(int)
    a = (pos - i0)[:, None]
    want = (1 - a) * src.root_translation[i0] + a * src.root_translation[i0 + 1]
    np.testing.assert_allclose(got.root_translation, want, atol=1e-5)
    assert not np.allclose(got.pose, load_motion(dataclasses.replace(cfg, tempo_variation=0.0), rig).pose)
    with pytest.raises(ValueError, match=r"tempo_variation 0.4.*lower bvh_start"):
        load_motion(dataclasses.replace(cfg, bvh_start=2600), rig)


def test_a_varying_tempo_hides_a_spring_phase_from_the_pose(rig_and_source):
    """On CMU 01_01's steady hops a spring on the pelvis' vertical acceleration swings in step with the hop, so the
    current pose tells it (R^2 > 0.5 on the test frames); played at small's varying tempo, the pose tells much
    less while the last 10 poses still tell it (docs/train.md "Springs on a periodic motion")."""
    from gsavatar.synth.fairness import history_fairness
    from gsavatar.synth.make import load_motion, split_frames
    from gsavatar.synth.motion_effects import effect_level, joint_signal
    from gsavatar.synth.render import pose_joint_positions

    rig, _ = rig_and_source
    names = [j.name for j in rig.joints]
    hem = next(e for e in PRESETS["small"].appearance.motion_effects if e.name == "hem")
    r2 = {}
    for tempo in (0.0, PRESETS["small"].tempo_variation):
        cfg = dataclasses.replace(preset("small"), decimate_to=3000, tempo_variation=tempo)
        m = load_motion(cfg, rig)
        joints = pose_joint_positions(rig, m.pose, m.root_rotation, m.root_translation)
        level = effect_level(hem, joint_signal(joints, names, hem, cfg.fps), cfg.fps)[0]
        train, test = (np.asarray(f) for f in split_frames(cfg))
        r = history_fairness(m, level[:, None], train, test, joints=joints)
        r2[tempo] = (r["pose_only"], r["history"])
    (p0, h0), (p1, h1) = r2[0.0], r2[PRESETS["small"].tempo_variation]
    assert p0 > 0.5 and h0 > 0.5, r2
    assert p1 < p0 - 0.3 and h1 > p1 + 0.4, r2
