"""benchmarks/trigger_capture.py: the controlled capture changes exactly the sleeve's signal and the light."""

from __future__ import annotations

import dataclasses

import pytest
from benchmark_modules import load_benchmark

from gsavatar.synth.presets import PRESETS, SynthConfig


@pytest.fixture(scope="module")
def trigger_capture():
    return load_benchmark("trigger_capture")


@pytest.mark.parametrize("signal", ["speed", "vertical_velocity", "height"])
def test_only_the_sleeve_signal_and_the_light_change(trigger_capture, signal):
    base = PRESETS["small_lit"]
    cfg = trigger_capture.trigger_config(signal)
    assert base.shading and not cfg.shading
    old = {e.name: e for e in base.appearance.motion_effects}
    new = {e.name: e for e in cfg.appearance.motion_effects}
    assert list(old) == list(new)
    assert new["sleeve"] == dataclasses.replace(old["sleeve"], signal=signal)
    assert all(new[k] == old[k] for k in old if k != "sleeve")
    # every other field of the preset is untouched
    strip = {"shading", "appearance"}
    assert {k: v for k, v in dataclasses.asdict(cfg).items() if k not in strip} == {
        k: v for k, v in dataclasses.asdict(base).items() if k not in strip
    }
    assert dataclasses.replace(cfg.appearance, motion_effects=()) == dataclasses.replace(
        base.appearance, motion_effects=()
    )


def test_an_unknown_signal_is_refused_before_rendering(trigger_capture):
    with pytest.raises(ValueError, match="sleeve.*unknown signal 'bogus'"):
        trigger_capture.trigger_config("bogus")


def test_drop_leaves_out_only_the_named_effects(trigger_capture):
    base = PRESETS["small_lit"]
    cfg = trigger_capture.trigger_config("height", ("sleeve",))
    old = {e.name: e for e in base.appearance.motion_effects}
    assert [e.name for e in cfg.appearance.motion_effects] == [n for n in old if n != "sleeve"]
    assert all(e == old[e.name] for e in cfg.appearance.motion_effects)
    assert not cfg.shading
    with pytest.raises(ValueError, match="motion effects are"):
        trigger_capture.trigger_config("height", ("cuff",))
    with pytest.raises(ValueError, match="no motion effect"):
        trigger_capture.trigger_config("height", tuple(old))


def test_dynamic_candidate_has_only_derivative_driven_effects(trigger_capture):
    cfg = trigger_capture.dynamic_config()
    base = {e.name: e for e in PRESETS["small_lit"].appearance.motion_effects}
    effects = {e.name: e for e in cfg.appearance.motion_effects}
    assert not cfg.shading and set(effects) == {"sweat", "hem", "flap"}
    assert all(e.signal in trigger_capture.DERIVATIVE_SIGNALS for e in effects.values())
    assert effects["sweat"] == dataclasses.replace(base["sweat"], strength=0.8)
    assert effects["hem"] == dataclasses.replace(base["hem"], y_range=(0.50, 0.70))
    assert effects["flap"].mechanism == "spring" and effects["flap"].region == base["sleeve"].region


def test_dynamic_drop_leaves_out_only_the_named_effects(trigger_capture):
    full = {e.name: e for e in trigger_capture.dynamic_config().appearance.motion_effects}
    cfg = trigger_capture.dynamic_config(("sweat",))
    assert [e.name for e in cfg.appearance.motion_effects] == [n for n in full if n != "sweat"]
    assert all(e == full[e.name] for e in cfg.appearance.motion_effects)
    with pytest.raises(ValueError, match="motion effects are"):
        trigger_capture.dynamic_config(("sleeve",))  # replaced by flap in the candidate
    with pytest.raises(ValueError, match="no motion effect"):
        trigger_capture.dynamic_config(tuple(full))


def test_second_springs_are_springs_on_derivatives_of_second(trigger_capture):
    cfg = trigger_capture.second_springs_config()
    base = PRESETS["second_lit"]
    assert not cfg.shading and cfg.bvh_path == base.bvh_path and cfg.seed == base.seed
    effects = cfg.appearance.motion_effects
    assert [e.name for e in effects] == ["swing", "sway", "kick"]
    assert all(e.mechanism == "spring" and e.signal in trigger_capture.DERIVATIVE_SIGNALS for e in effects)
    assert SynthConfig.from_json(cfg.to_json()) == cfg
    # the experiment became the `second` preset: the same capture but for the preset's name
    assert dataclasses.replace(cfg, preset="second") == PRESETS["second"]


def test_small_is_the_springs_candidate_at_a_varying_tempo(trigger_capture):
    """`small` = the measured springs-only candidate (dynamic_config without sweat) played at a varying tempo."""
    cand = trigger_capture.dynamic_config(("sweat",))
    small = PRESETS["small"]
    assert small.tempo_variation > 0 and cand.tempo_variation == 0 and not small.shading
    assert dataclasses.replace(cand, preset="small", tempo_variation=small.tempo_variation) == small
