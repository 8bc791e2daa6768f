"""The training configuration as one tree (runs/config.py): every model and schedule field a flag of
``avatar-train avatar``, presets as named default instances, ``None`` for "the preset's", and run configs of
earlier versions still loading through the one generic reader."""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path

import pytest
import tyro

from gsavatar.models.config import VARIANTS, ModelConfig, model_preset, variant_config
from gsavatar.runs.config import (
    PRESET_SCHEDULES,
    Schedule,
    TrainConfig,
    from_json,
    preset_config,
    read_config,
    resolve,
    to_json,
    upgrade_run_json,
)
from gsavatar.train.cli import Avatar, _preset_default
from gsavatar.utils.errors import SchemaError

DATA = Path(__file__).parent.parent / "data" / "run_configs"
BASE = ["--dataset", "ds", "--out", "run"]


def parse(args: list[str]) -> TrainConfig:
    """``avatar-train avatar ARGS`` parsed (no training)."""
    return tyro.cli(Avatar, default=_preset_default(args), args=args).train


def other_value(flag: str, hint, value):
    """A valid value of the field's type that differs from ``value``, and its command-line spelling."""
    if typing.get_origin(hint) is tuple:
        new = (32, 16)
        return new, [flag, *(str(x) for x in new)]
    if typing.get_origin(hint) is typing.Literal:
        new = next(a for a in typing.get_args(hint) if a != value)
        return new, [flag, str(new)]
    if hint is bool:  # --model.x / --model.no-x
        return (not value), [flag if not value else flag.replace("--model.", "--model.no-")]
    if hint is int:
        return value + 1, [flag, str(value + 1)]
    if hint is float:
        return value * 0.5, [flag, repr(value * 0.5)]
    raise AssertionError(f"no test value for {hint}")


MODEL_HINTS = typing.get_type_hints(ModelConfig)


@pytest.mark.parametrize("name", list(MODEL_HINTS))
def test_every_model_field_is_a_flag(name):
    base = parse([*BASE, "--preset", "small"]).model
    new, spelt = other_value(f"--model.{name.replace('_', '-')}", MODEL_HINTS[name], getattr(base, name))
    got = parse([*BASE, "--preset", "small", *spelt]).model
    assert getattr(got, name) == new
    assert dataclasses.replace(got, **{name: getattr(base, name)}) == base  # only that field changed


SCHEDULE_VALUES = {
    "steps": (7, "7"),
    "batch_size": (3, "3"),
    "image_scale": (0.5, "0.5"),
    "correctives_step": (4, "4"),
    "checkpoint_every": (5, "5"),
    "basis_lr_scale": (2.0, "2.0"),
    "vae_noise_step": ("never", "never"),
    "sh_increase_fraction": (0.25, "0.25"),
}


def test_every_schedule_field_is_a_flag():
    assert set(SCHEDULE_VALUES) == {f.name for f in dataclasses.fields(Schedule)}
    for name, (value, spelt) in SCHEDULE_VALUES.items():
        got = parse([*BASE, "--preset", "paper", f"--schedule.{name.replace('_', '-')}", spelt]).schedule
        assert getattr(got, name) == value, name
    assert parse([*BASE, "--schedule.vae-noise-step", "12"]).schedule.vae_noise_step == 12
    # the short forms of the common schedule flags, as scripts and the docs spell them
    got = parse([*BASE, "--steps", "9", "--correctives-step", "3", "--image-scale", "0.25"]).schedule
    assert (got.steps, got.correctives_step, got.image_scale) == (9, 3, 0.25)


@pytest.mark.parametrize("preset", ["tiny", "small", "paper"])
@pytest.mark.parametrize("variant", ["ours", "mmlps_dagger"])
def test_presets_are_named_default_instances(preset, variant):
    """The flags start from the preset's model (with the variant) and schedule, wherever --preset stands."""
    got = parse(["--variant", variant, *BASE, f"--preset={preset}"])
    assert got.model == variant_config(model_preset(preset), variant)
    sched = PRESET_SCHEDULES[preset]
    assert got.schedule == sched and sched.resolved()
    assert resolve(got).schedule.vae_noise_step == (
        sched.correctives_step if sched.vae_noise_step == "correctives" else sched.vae_noise_step
    )


def test_unset_means_the_preset_and_never_is_its_own_value():
    cfg = TrainConfig(dataset=Path("ds"), out=Path("run"), preset="paper")
    assert cfg.model is None and not cfg.schedule.resolved()
    r = resolve(cfg)
    assert r.model == model_preset("paper") and r.schedule.resolved()
    assert r.schedule.vae_noise_step == r.schedule.correctives_step == 500  # the paper's: with the correctives
    never = resolve(dataclasses.replace(cfg, schedule=Schedule(vae_noise_step="never", steps=10)))
    assert never.schedule.vae_noise_step == "never" and never.schedule.steps == 10
    own = model_preset("tiny").replace(latent_sh0=False)
    assert resolve(dataclasses.replace(cfg, model=own)).model == own  # a given model is kept as it is


def test_resolved_config_round_trips_through_json():
    cfg = resolve(preset_config(Path("ds"), Path("run"), "small", "wo_local_pca", lpips_weights=Path("w.pth")))
    text = json.loads(json.dumps({"train": to_json(cfg), "model": cfg.model.to_json()}))
    assert "model" not in text["train"]  # written once, beside it (resuming checks it against the checkpoint)
    assert from_json(text["train"], "config.json", model=text["model"]) == cfg


@pytest.mark.parametrize("file", sorted(p.name for p in DATA.glob("*.json")))
def test_run_configs_of_earlier_versions_still_load(file):
    """config.json of earlier layouts (flat schedule fields with 0 / -1 / -2 for "the preset's" and "never";
    models without the fields added since): read by the same reader, meaning what they meant."""
    saved = json.loads((DATA / file).read_text())
    old = saved["train"]
    cfg = resolve(from_json(old, DATA / file, model=saved["model"]))
    s = cfg.schedule
    assert (s.steps, s.batch_size, s.image_scale, s.correctives_step, s.checkpoint_every) == (
        old["steps"],
        old["batch_size"],
        old["image_scale"],
        old["correctives_step"],
        old["checkpoint_every"],
    )
    if "vae_noise_step" in old:
        assert old["vae_noise_step"] == -1 and s.vae_noise_step == "never"
    if "basis_lr_scale" in old:
        assert s.basis_lr_scale == old["basis_lr_scale"]
    assert cfg.max_steps_this_run is None  # 0 meant "to the end"
    assert cfg.model.hidden == tuple(saved["model"]["hidden"])
    defaults = ModelConfig()
    for f in dataclasses.fields(ModelConfig):  # fields the file lacks take the defaults (the old behaviour)
        if f.name not in saved["model"]:
            assert getattr(cfg.model, f.name) == getattr(defaults, f.name), f.name
    # a checkpoint's copy of such a config compares like with like with today's layout (resuming)
    up = upgrade_run_json(saved)
    assert up["train"]["schedule"]["batch_size"] == old["batch_size"] and "batch_size" not in up["train"]
    assert upgrade_run_json(up) == up


def test_old_sentinels_become_none():
    old = json.loads((DATA / "v2026-12-03_flat_schedule.json").read_text())["train"]
    old = {**old, "steps": 0, "image_scale": 0, "correctives_step": -1, "vae_noise_step": -2, "basis_lr_scale": 0}
    s = from_json(old, "config.json").schedule
    assert (s.steps, s.image_scale, s.correctives_step, s.vae_noise_step, s.basis_lr_scale) == (None,) * 5
    assert resolve(from_json(old, "config.json")).schedule == PRESET_SCHEDULES["tiny"]


def test_the_reader_names_the_bad_field():
    cfg = resolve(TrainConfig(dataset=Path("ds"), out=Path("run")))
    good = to_json(cfg)
    with pytest.raises(SchemaError, match=r"train\.schedule\.steps"):
        from_json({**good, "schedule": {**good["schedule"], "steps": "many"}}, "config.json")
    with pytest.raises(SchemaError, match=r"train\.schedule\.vae_noise_step"):
        from_json({**good, "schedule": {**good["schedule"], "vae_noise_step": "sometimes"}}, "config.json")
    with pytest.raises(SchemaError, match=r"train\.losses\.l1"):
        from_json({**good, "losses": {**good["losses"], "l1": True}}, "config.json")
    with pytest.raises(SchemaError, match=r"model\.latent_sh1"):
        read_config(ModelConfig, {"latent_sh1": True}, "config.json", "model", unknown="error")
    with pytest.raises(SchemaError, match=r"model\.mlp_init"):
        read_config(ModelConfig, {"mlp_init": "xavier"}, "config.json", "model", unknown="error")


def test_no_code_patches_a_module_level_recipe():
    """Experiments pass a model (TrainConfig.model / --model.*) instead of rewriting CPU_RECIPE."""
    root = Path(__file__).parents[2]
    for path in [*(root / "benchmarks").glob("*.py"), *(root / "src").rglob("*.py")]:
        text = path.read_text()
        assert "CPU_RECIPE =" not in text or path.name == "config.py", path
        assert ".CPU_RECIPE[" not in text, path
    assert set(VARIANTS) >= {"ours", "mmlps_dagger"}


def test_a_refused_nested_value_exits_2_naming_it(capsys, tmp_path):
    from gsavatar.train.cli import main

    try:
        rc = main(["avatar", *BASE[:2], "--out", str(tmp_path / "r"), "--model.init-opacity", "2"])
    except SystemExit as e:  # tyro's parse errors exit through SystemExit
        rc = e.code
    assert rc == 2 and "init_opacity" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # refused before anything is written
