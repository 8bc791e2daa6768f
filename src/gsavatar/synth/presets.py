"""Configuration of synthetic capture builds (:func:`gsavatar.synth.make.make_capture`).

Presets:

- ``tiny``: decimated body (~3k vertices), 6 cameras of 128x128, 12 frames, 256^2
  texture. For unit tests: builds in seconds once the Anny cache exists.
- ``small``: the demo capture: full body (~13.5k vertices), 12 cameras of 256x256, 450 frames at 30 fps (15 s of
  CMU 01_01's hops played at a varying tempo; the last 90 are the test segment), 512^2 texture, evenly lit (albedo
  only), and appearance that the motion's history causes (:data:`SMALL_SPRINGS`: two springs driven by the
  pelvis' and the feet's vertical acceleration) on top of weak pose-independent folds and drifts. A few minutes on
  2 cores.
- ``small_lit``: the demo capture until 2026-12-08: the same motion at its captured tempo, lit by a light fixed in
  the room, with an accumulator, a hysteresis on the right hand's height and a spring (:data:`SMALL_MOTION_EFFECTS`).
- ``small_random``: the capture before that (120 frames, a shirt that switches between three dyes independently of
  the motion): what re-initialising the predictor is for.
- ``second``: another body, seed and CMU motion (01_03, walking on uneven terrain, 900 frames), evenly lit, three
  springs on other signals, body parts and parameters (:data:`SECOND_SPRINGS`).
- ``second_lit``: ``second``'s body and motion lit, with :data:`SECOND_MOTION_EFFECTS` (an accumulator, a
  hysteresis on the knee's speed, a spring).
- ``hard``: stability stressors for texture projection/fusion: a sparse dome (texels
  seen by a single view), grazing top-down and floor-level cameras, a camera pointed
  away (sees nothing), a box occluding part of the body in one view only, and one
  corrupted view (strong colour cast + noise in half of its frames) that median-band
  fusion must reject.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from gsavatar.synth.appearance import AppearanceConfig
from gsavatar.synth.cameras import SpecialKind
from gsavatar.synth.motion_effects import MotionEffect
from gsavatar.utils.jsonio import config_to_json

PresetName = Literal["tiny", "small", "small_lit", "small_random", "second", "second_lit", "hard"]
DEFAULT_BVH = "/usr/share/assimp/models/BVH/01_01.bvh"


@dataclass(frozen=True)
class SynthConfig:
    """Everything that determines a synthetic capture (saved as ``gt/config.json``)."""

    preset: str = "small"
    """Name of the preset this config came from (recorded in ``gt/config.json``)."""
    seed: int = 0
    """Seed of everything random (appearance, camera jitter, corruption); same seed -> same bytes."""
    body_seed: int = 0
    """Anny phenotype: 0 = the default average body, else a random adult drawn from this seed."""
    decimate_to: int | None = None
    """Target vertex count of the body mesh (quadric decimation), or None for the full mesh."""
    num_cams: int = 12
    """Cameras of the dome, split evenly between full-, upper- and lower-body views."""
    width: int = 256
    """Image width, pixels."""
    height: int = 256
    """Image height, pixels."""
    distortion: bool = True
    """Give about half the dome cameras a small lens distortion (|k1| <= 0.05)."""
    cam_radius: float = 3.2
    """Distance of the dome cameras from the body's vertical axis, metres."""
    num_frames: int = 120
    """Frames F of the capture."""
    fps: float = 30.0
    """Frame rate the mocap is resampled to."""
    bvh_path: str = DEFAULT_BVH
    """Motion capture (CMU BVH) that drives the body."""
    bvh_start: int = 960
    """First SOURCE frame of the BVH segment (01_01 is 120 fps; 960 = 8 s, just before a turn-around)."""
    tempo_variation: float = 0.0
    """Log standard deviation of the motion's playback rate (0: as captured). A smooth random tempo (0.35: about
    0.5-1.6x) makes a cyclic motion reach the same poses at other speeds, so states driven by its derivatives are
    no longer a function of the pose (:func:`gsavatar.synth.make.tempo_curve`)."""
    tempo_smoothing_s: float = 1.0
    """Time scale of the tempo's changes, seconds."""
    root_xz: Literal["keep", "center", "treadmill"] = "treadmill"
    """Horizontal root motion: ``keep`` as captured; ``center`` subtract the segment mean; ``treadmill``
    subtract a Gaussian-smoothed trajectory too, so travelling motion (01_01 hops 3.5 m) stays in the dome."""
    treadmill_sigma_s: float = 0.6
    """Smoothing of the trajectory ``treadmill`` removes, seconds."""
    tex_size: int = 512
    """Resolution of the ground-truth UV texture (square)."""
    supersample: int = 2
    """Rays per pixel along each axis (2 -> 2x2), anti-aliases edges and mask coverage."""
    shading: bool = True
    """Lambertian shading (ambient 0.65 + 0.35 diffuse) on top of the albedo; False renders the albedo."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour, RGB in [0, 1]."""
    test_fraction: float = 0.2
    """Fraction of frames held out as the test segment (the tail of the sequence)."""
    test_cameras: int = 1
    """Cameras held out for test: 1 = ``full01``; 2 adds the frontal ``upper00``; 3 the frontal ``lower00``."""
    coupled_param: str | None = None
    """Pose parameter the trouser folds follow in train frames; None = the ``RightHand`` (else right-hand
    group) parameter that varies most over the train frames."""
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    """Time-varying ground-truth appearance."""
    special_cameras: tuple[SpecialKind, ...] = ()
    """Extra stress views: ``top`` (grazing, from above), ``floor`` (grazing, from the feet), ``away`` (sees
    nothing)."""
    occluded_camera: str | None = None
    """Dome camera that sees a box occluding part of the body (only that view has the box)."""
    corrupted_camera: str | None = None
    """Dome camera whose images get a strong colour cast and noise in some frames."""
    corrupted_fraction: float = 0.5
    """Fraction of frames in which ``corrupted_camera`` is corrupted."""
    workers: int = 0
    """Render processes; 0 = one per CPU core, 1 = in this process."""

    def to_json(self) -> dict:
        """Plain-JSON form for ``gt/config.json``; ``workers`` is left out (it never changes the output)."""
        return config_to_json(self, exclude=("workers",))

    @classmethod
    def from_json(cls, d: dict) -> SynthConfig:
        """Inverse of :meth:`to_json` (e.g. to rebuild a capture from its ``gt/config.json``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown SynthConfig fields {sorted(unknown)}")
        kw = dict(d)
        if "appearance" in kw:
            app = dict(kw["appearance"])
            if "motion_effects" in app:
                app["motion_effects"] = tuple(
                    MotionEffect(**{k: tuple(v) if isinstance(v, list) else v for k, v in e.items()})
                    for e in app["motion_effects"]
                )
            kw["appearance"] = AppearanceConfig(**app)
        for k in ("background", "special_cameras"):
            if k in kw:
                kw[k] = tuple(kw[k])
        return cls(**kw)


_LIMBS = ("left_hand", "right_hand", "left_foot", "right_foot")
SMALL_MOTION_EFFECTS = (
    # Sustained limb effort darkens the upper shirt (sweat) and fades within about a second.
    MotionEffect(
        "sweat",
        "accumulator",
        "speed",
        _LIMBS,
        "shirt",
        "darken",
        strength=0.5,
        y_range=(0.66, 0.86),
        time_constant_s=0.6,
        reference_quantile=0.7,
    ),
    # The trousers' dye flips when the right hand rises high and stays until it drops low (a pushed-up sleeve).
    MotionEffect(
        "sleeve",
        "hysteresis",
        "height",
        ("right_hand",),
        "trousers",
        "dye",
        color=(1.5, 0.8, 0.55),
        low_quantile=0.25,
        high_quantile=0.75,
    ),
    # The shirt's hem swings after the pelvis moves up or down: a damped spring on its vertical acceleration.
    MotionEffect(
        "hem",
        "spring",
        "vertical_acceleration",
        ("pelvis",),
        "shirt",
        "tint",
        strength=1.2,
        relative_to=None,
        y_range=(0.56, 0.66),
        frequency_hz=1.5,
        damping=0.3,
    ),
)
"""The ``small_lit`` capture's history-caused appearance (the demo's until 2026-12-08; docs/synth.md)."""
SECOND_MOTION_EFFECTS = (
    MotionEffect(
        "flush",
        "accumulator",
        "speed",
        _LIMBS,
        "shirt",
        "dye",
        color=(1.35, 0.8, 0.7),
        time_constant_s=0.5,
        reference_quantile=0.6,
    ),
    # The trousers' dye flips on a fast knee move and stays until the leg is still (a cuff that rides up). The
    # round before it flipped on the pelvis' vertical velocity beyond its 10/90% quantiles: 3 flips in the 360
    # training frames, 5 in the 90 test frames, which no predictor can learn (docs/train.md).
    MotionEffect(
        "cuff",
        "hysteresis",
        "speed",
        ("left_knee",),
        "trousers",
        "dye",
        color=(0.7, 0.9, 1.5),
        low_quantile=0.25,
        high_quantile=0.75,
    ),
    MotionEffect(
        "swing",
        "spring",
        "vertical_acceleration",
        ("pelvis",),
        "shirt",
        "band",
        strength=0.05,
        color=(0.95, 0.92, 0.85),
        relative_to=None,
        y_range=(0.57, 0.65),
        frequency_hz=1.5,
        damping=0.4,
    ),
)
"""The ``second_lit`` capture's: other mechanisms' parameters, regions and effects, another motion and body."""
SMALL_SPRINGS = (
    # The trousers flap after the feet push off or land: a slower spring on the feet's vertical acceleration dyes
    # them.
    MotionEffect(
        "flap",
        "spring",
        "vertical_acceleration",
        ("left_foot", "right_foot"),
        "trousers",
        "dye",
        color=(1.5, 0.8, 0.55),
        relative_to=None,
        frequency_hz=1.2,
        damping=0.3,
    ),
    # The shirt's hem swings after the pelvis moves up or down: a damped spring on its vertical acceleration tints a
    # band of the shirt around the waist.
    MotionEffect(
        "hem",
        "spring",
        "vertical_acceleration",
        ("pelvis",),
        "shirt",
        "tint",
        strength=1.2,
        relative_to=None,
        y_range=(0.50, 0.70),
        frequency_hz=1.5,
        damping=0.3,
    ),
)
"""The ``small`` capture's history-caused appearance: two springs (docs/synth.md). On CMU 01_01's steady hops a
spring swings in step with the hop, so its phase is a function of the pose; the preset plays the motion at a varying
tempo (``tempo_variation``) so that identical poses are reached at other speeds and the springs' states differ
between them (docs/train.md "Springs on a periodic motion")."""
SECOND_SPRINGS = (
    # A light band on the shirt's hem moves after the chest rises or drops.
    MotionEffect(
        "swing",
        "spring",
        "vertical_acceleration",
        ("chest",),
        "shirt",
        "band",
        strength=0.06,
        color=(0.95, 0.92, 0.85),
        relative_to=None,
        y_range=(0.57, 0.65),
        frequency_hz=1.5,
        damping=0.4,
    ),
    # The upper shirt's hue sways after the head rises or drops.
    MotionEffect(
        "sway",
        "spring",
        "vertical_acceleration",
        ("head",),
        "shirt",
        "tint",
        strength=1.0,
        relative_to=None,
        y_range=(0.68, 0.86),
        frequency_hz=1.3,
        damping=0.3,
    ),
    # The trousers' dye kicks after the feet move up or down (a spring on their vertical velocity).
    MotionEffect(
        "kick",
        "spring",
        "vertical_velocity",
        ("left_foot", "right_foot"),
        "trousers",
        "dye",
        color=(0.7, 0.9, 1.5),
        relative_to=None,
        frequency_hz=1.0,
        damping=0.35,
    ),
)
"""The ``second`` capture's: three springs on other signals, body parts, regions and parameters than ``small``'s,
on CMU 01_03 (walking on uneven terrain, which does not repeat a cycle)."""
_QUIET = dict(fold_strength=0.12, hair_hue_range=0.3)  # pose-independent changes kept, but small
_SMALL = SynthConfig(
    preset="small",
    tex_size=512,
    test_cameras=2,
    num_frames=450,
    bvh_start=120,
    tempo_variation=0.35,
    shading=False,
    appearance=AppearanceConfig(motion_effects=SMALL_SPRINGS, **_QUIET),
)
_SECOND = SynthConfig(
    preset="second",
    seed=1,
    body_seed=3,
    tex_size=512,
    test_cameras=2,
    num_frames=900,  # 720 training frames: 360 were too few for a spring and a hysteresis (docs/train.md)
    bvh_path="/usr/share/assimp/models/BVH/01_03.bvh",
    bvh_start=0,
    shading=False,
    appearance=AppearanceConfig(motion_effects=SECOND_SPRINGS, **_QUIET),
)

PRESETS: dict[str, SynthConfig] = {
    "tiny": SynthConfig(
        preset="tiny",
        decimate_to=3000,
        num_cams=6,
        width=128,
        height=128,
        num_frames=12,
        fps=15.0,
        bvh_start=1040,
        tex_size=256,
        test_fraction=0.25,
        test_cameras=1,
        appearance=AppearanceConfig(fold_dwell_s=0.25, drift_period_s=2.0, face_period_s=0.8),
    ),
    "small": _SMALL,
    # the lit captures: the light fixed in the room, the motion at its own tempo, other mechanisms
    "small_lit": dataclasses.replace(
        _SMALL,
        preset="small_lit",
        tempo_variation=0.0,
        shading=True,
        appearance=AppearanceConfig(motion_effects=SMALL_MOTION_EFFECTS, **_QUIET),
    ),
    "small_random": SynthConfig(
        preset="small_random",
        tex_size=512,
        test_cameras=2,
        appearance=AppearanceConfig(dye_garment="shirt", dye_states=3, dye_dwell_s=1.0),
    ),
    "second": _SECOND,
    "second_lit": dataclasses.replace(
        _SECOND,
        preset="second_lit",
        shading=True,
        appearance=AppearanceConfig(motion_effects=SECOND_MOTION_EFFECTS, **_QUIET),
    ),
    "hard": SynthConfig(
        preset="hard",
        decimate_to=6000,
        num_cams=9,
        width=192,
        height=192,
        num_frames=24,
        fps=15.0,
        bvh_start=1000,
        tex_size=512,
        test_cameras=1,
        special_cameras=("top", "floor", "away"),
        occluded_camera="full02",
        corrupted_camera="upper01",
        corrupted_fraction=0.5,
        appearance=AppearanceConfig(fold_dwell_s=0.5, drift_period_s=3.0),
    ),
}


PRESET_HELP: dict[str, str] = {
    "tiny": "unit-test capture: ~3k-vertex body, 6 cameras 128x128, 12 frames, 256^2 texture (seconds)",
    "small": "demo capture: full body, 12 cameras 256x256, 450 frames at 30 fps (90 test) of CMU 01_01 at a varying "
    "tempo, 512^2 texture, evenly lit, appearance caused by the motion's history (two springs; minutes)",
    "small_lit": "the demo capture until 2026-12-08: small's motion at its own tempo, lit by a light fixed in the "
    "room, an accumulator, a hysteresis on the hand's height and a spring",
    "small_random": "the capture before that: 120 frames, appearance random in time (shirt dye switches)",
    "second": "a second capture: another body and seed, 900 frames of CMU 01_03 (180 test), evenly lit, three "
    "springs on other signals and parts (minutes)",
    "second_lit": "second's body and motion lit by a light fixed in the room, with an accumulator, a hysteresis on "
    "the knee's speed and a spring",
    "hard": "stress capture: sparse dome + grazing/away cameras, one occluded and one corrupted view",
}


def preset(name: PresetName, **overrides) -> SynthConfig:
    """A named preset, optionally with some fields replaced (``preset("tiny", seed=3)``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides)
