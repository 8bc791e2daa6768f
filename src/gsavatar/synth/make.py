"""Build a synthetic multi-view capture (capture format v1) plus its ground truth.

``make_capture(cfg, out_dir, anny_cache_dir)`` writes::

    out_dir/
      capture.json calibration.json splits.json      (written LAST: a killed build never looks complete)
      template/  mesh.obj rig.json skin_weights.npz face_uv_mask.png
      motion.npz pose, root_rotation, root_translation, face [F, 4]
      images/{cam}/{frame:08d}.png   8-bit sRGB-agnostic RGB (albedo x mild shading)
      masks/{cam}/{frame:08d}.png    body coverage 0..255 (occluders and background are 0)
      gt/textures/{frame:08d}.png    the UNSHADED UV albedo of each frame (PSNR reference)
      gt/states.json                 per-frame appearance states, the spurious coupling,
                                     corrupted/occluded/special cameras, camera kinds
      gt/regions.npz                 UV maps of the garment/skin/hair/face regions (uint8)
      gt/texel_views.npz             views seeing each texel at frame 0 (uint8 [S, S])
      gt/config.json                 the SynthConfig
      gt/motion_states.npz           history-caused appearance states [F, E] and their signals (if any)
      gt/fairness.json               how well pose alone / the pose history predict those states

The body is the Anny model (:mod:`gsavatar.synth.body`), the motion a CMU BVH clip
retargeted onto it (:mod:`gsavatar.motion.retarget`), the appearance
:class:`~gsavatar.synth.appearance.AppearanceModel`, the images ray cast by
:mod:`gsavatar.synth.render`. Same config and seed -> byte-identical files: every frame
is rendered independently with single-threaded Embree, frames are spread over a
process pool (``cfg.workers``).

CLI: ``python -m gsavatar.synth.make --preset tiny --out /tmp/cap`` (see :func:`main`).
"""

from __future__ import annotations

import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from gsavatar.data_schema.capture import Camera, Motion, Split, write_capture_metadata
from gsavatar.data_schema.rig import BODY_GROUPS, Rig
from gsavatar.data_schema.template import save_template
from gsavatar.motion.resample import resample_motion_at, times_at
from gsavatar.motion.retarget import motion_from_bvh_file
from gsavatar.synth.appearance import AppearanceModel
from gsavatar.synth.body import build_anny_body, default_anny_cache
from gsavatar.synth.cameras import camera_kind, make_dome, special_cameras
from gsavatar.synth.fairness import history_fairness
from gsavatar.synth.presets import PRESET_HELP, PRESETS, SynthConfig
from gsavatar.synth.render import (
    FrameScene,
    Shading,
    TriMesh,
    box_mesh,
    pose_joint_positions,
    pose_vertices,
    render_view,
    supersampled_rays,
    texel_visibility,
)
from gsavatar.utils.cli import run_reporting_errors
from gsavatar.utils.io import atomic_save_npz, atomic_write_json, write_image
from gsavatar.utils.outdir import claim_output_dir

GT_FORMAT = "gsavatar-synth-gt"
GT_VERSION = 1


# --------------------------------------------------------------------------- motion
def tempo_curve(cfg: SynthConfig) -> np.ndarray:
    """Playback rate of the motion at each output frame: ``exp(tempo_variation z_t)`` with ``z`` Gaussian noise
    smoothed over ``tempo_smoothing_s`` and scaled to unit standard deviation (seeded by ``cfg.seed``); all ones
    when ``tempo_variation`` is 0. [F] float64"""
    from scipy.ndimage import gaussian_filter1d

    F = cfg.num_frames
    if cfg.tempo_variation == 0:
        return np.ones(F)
    if not (cfg.tempo_variation > 0 and cfg.tempo_smoothing_s > 0):
        raise ValueError(
            f"need tempo_variation >= 0 and tempo_smoothing_s > 0, got {cfg.tempo_variation}, {cfg.tempo_smoothing_s}"
        )
    sigma = cfg.tempo_smoothing_s * cfg.fps
    pad = int(np.ceil(4 * sigma))
    z = gaussian_filter1d(np.random.default_rng([cfg.seed, 47]).standard_normal(F + 2 * pad), sigma)[pad : pad + F]
    z = (z - z.mean()) / max(float(z.std()), 1e-12)
    return np.exp(cfg.tempo_variation * z)


def load_motion(cfg: SynthConfig, rig: Rig) -> Motion:
    """The BVH segment retargeted onto ``rig`` at ``cfg.fps`` with the ``cfg.root_xz`` treatment, played at the
    varying rate of :func:`tempo_curve` when ``cfg.tempo_variation > 0`` (the same poses reached at other
    speeds: what makes a spring's phase differ between visits of one pose on a repeated cycle)."""
    from scipy.ndimage import gaussian_filter1d

    if cfg.tempo_variation == 0:
        m = motion_from_bvh_file(cfg.bvh_path, rig, fps_out=cfg.fps, start=cfg.bvh_start, count=cfg.num_frames)
        got = len(m.pose)
    else:
        rate = tempo_curve(cfg)
        src = motion_from_bvh_file(cfg.bvh_path, rig, fps_out=None, start=cfg.bvh_start)  # every source frame
        pos = np.concatenate([[0.0], np.cumsum(rate[:-1])]) * (src.fps / cfg.fps)  # source frame of each output
        got = int(np.searchsorted(pos, len(src.pose) - 1, side="right"))
        if got >= cfg.num_frames:
            pose, rr, rt, _ = resample_motion_at(
                src.pose, src.root_rotation, src.root_translation, None, rig, times_at(pos, len(src.pose))
            )
            m = src._replace(pose=pose, root_rotation=rr, root_translation=rt, fps=cfg.fps)
    if got != cfg.num_frames:
        raise ValueError(
            f"{cfg.bvh_path}: only {got} frames from source frame {cfg.bvh_start} at {cfg.fps} fps"
            + (f" (tempo_variation {cfg.tempo_variation})" if cfg.tempo_variation else "")
            + f", num_frames={cfg.num_frames} requested; lower bvh_start or num_frames"
        )
    t = m.root_translation.astype(np.float64).copy()
    if cfg.root_xz in ("center", "treadmill"):
        t[:, [0, 2]] -= t[:, [0, 2]].mean(0)
    if cfg.root_xz == "treadmill":
        t[:, [0, 2]] -= gaussian_filter1d(t[:, [0, 2]], cfg.treadmill_sigma_s * cfg.fps, axis=0, mode="nearest")
    return Motion(m.pose.astype(np.float32), m.root_rotation.astype(np.float32), t.astype(np.float32))


def coupling_slot(rig: Rig, pose: np.ndarray, train_frames: np.ndarray, name: str | None) -> tuple[int, str]:
    """Pose slot (and parameter name) the trouser folds follow in train frames. pose [F, P]."""
    slots = rig.slot_params()
    names = [rig.params[i].name for i in slots]
    if name is not None:
        if name not in names:
            raise ValueError(f"coupled_param {name!r} is not a pose parameter of the rig")
        return names.index(name), name
    std = pose[train_frames].std(0)
    groups = rig.slot_groups()
    joint_of = [rig.params[i].joint for i in slots]
    for pick in (
        lambda s: joint_of[s] == "RightHand",
        lambda s: BODY_GROUPS[groups[s]] == "right_hand",
        lambda s: BODY_GROUPS[groups[s]] == "right_arm",
        lambda s: True,
    ):
        cand = [s for s in range(len(slots)) if pick(s)]
        if cand and std[cand].max() > 1e-4:
            s = int(max(cand, key=lambda i: std[i]))
            return s, names[s]
    return 0, names[0]


def split_frames(cfg: SynthConfig) -> tuple[list[int], list[int]]:
    """Train and test frames: the test segment is the tail ``test_fraction`` of the frames (at least one of each)."""
    F = cfg.num_frames
    if F < 2:
        raise ValueError(f"num_frames must be >= 2 to split train/test, got {F}")
    n_test = min(F - 1, max(1, int(round(F * cfg.test_fraction))))
    return list(range(F - n_test)), list(range(F - n_test, F))


def default_splits(cfg: SynthConfig, cameras: dict[str, Camera]) -> dict[str, Split]:
    """Test = the tail ``test_fraction`` of the frames (:func:`split_frames`) and 1-3 held-out dome cameras."""
    train, test = split_frames(cfg)
    wanted = [c for c in ("full01", "upper00", "lower00")[: cfg.test_cameras] if c in cameras]
    if not wanted:
        wanted = [next(iter(cameras))]
    train_cams = [c for c in cameras if c not in wanted]
    if not train_cams:
        raise ValueError("need at least one training camera besides the held-out test cameras")
    return {"train": Split(train, train_cams), "test": Split(test, wanted)}


# --------------------------------------------------------------------------- per-frame work
@dataclass
class _RenderJob:
    """Everything a render worker needs (sent once per worker process)."""

    out: Path
    faces: np.ndarray  # [F, 3]
    corner_uvs: np.ndarray  # [F, 3, 2]
    vertices: np.ndarray  # [N, V, 3] posed, world
    cameras: dict[str, Camera]
    appearance: AppearanceModel
    supersample: int
    shading: Shading | None
    background: tuple[float, float, float]
    occluders: dict[str, list[TriMesh]]
    corrupted_camera: str | None
    corrupted_frames: frozenset[int]
    seed: int
    rays: dict[str, np.ndarray] | None = None


_JOB: _RenderJob | None = None  # set once per worker process by _init_worker


def _init_worker(job: _RenderJob) -> None:
    global _JOB
    job.rays = {n: supersampled_rays(c, job.supersample) for n, c in job.cameras.items()}
    _JOB = job


def corrupt_image(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A misfiring camera: wrong exposure (x0.55 or x1.6), a colour cast and sensor noise.

    The exposure error moves luminance far outside the [0.8, 1.1] x median band, which is
    the failure median-band fusion is designed to reject; a pure hue cast at constant
    luminance would pass any luminance test. img [H, W, 3] in [0, 1] -> same shape.
    """
    exposure = np.float32(rng.choice([0.55, 1.6]))
    cast = rng.permutation(np.array([1.15, 1.0, 0.85], np.float32))
    noise = rng.normal(0.0, 0.05, img.shape).astype(np.float32)
    return np.clip(img * exposure * cast + noise, 0.0, 1.0)


def _render_frame(frame: int) -> dict:
    job = _JOB
    tex = job.appearance.texture(frame)
    write_image(job.out / "gt" / "textures" / f"{frame:08d}.png", tex)
    verts = job.vertices[frame]
    scene = FrameScene(verts, job.faces, job.corner_uvs, nthreads=1)
    means = {}
    views = None
    if frame == 0:
        uv = job.appearance.uv
        cov = np.flatnonzero(uv.covered.ravel())
        t_face, t_bary = uv.face_id.ravel()[cov], uv.bary.reshape(-1, 3)[cov]
        views = np.zeros(tex.shape[0] * tex.shape[1], np.uint8)
    for name, cam in job.cameras.items():
        sc = scene
        if job.occluders.get(name):
            sc = FrameScene(verts, job.faces, job.corner_uvs, extras=job.occluders[name], nthreads=1)
        r = render_view(
            sc,
            cam,
            tex,
            supersample=job.supersample,
            shading=job.shading,
            background=job.background,
            rays=job.rays[name],
        )
        img = r.image
        if name == job.corrupted_camera and frame in job.corrupted_frames:
            img = corrupt_image(img, np.random.default_rng([job.seed, 7919, frame]))
        write_image(job.out / "images" / name / f"{frame:08d}.png", img)
        write_image(job.out / "masks" / name / f"{frame:08d}.png", r.mask)
        means[name] = img.reshape(-1, 3).mean(0).tolist()
        if views is not None:
            views[cov] += texel_visibility(sc, t_face, t_bary, cam).astype(np.uint8)
    return {"frame": frame, "mean_color": means, "views": views}


# --------------------------------------------------------------------------- build
def make_capture(
    cfg: SynthConfig, out_dir: str | Path, anny_cache_dir: str | Path, progress: bool = True, overwrite: bool = False
) -> Path:
    """Write a synthetic capture (format v1) and its ``gt/`` folder to ``out_dir``. Returns ``out_dir``.

    anny_cache_dir: Anny's model-data cache (``ANNY_CACHE_DIR``; built on first use, ~80 s).
    overwrite: replace an existing capture in ``out_dir`` (its images/, masks/, gt/ and
        template/ folders are removed first); otherwise an existing capture is an error.
    """
    out = Path(out_dir)
    if (out / "capture.json").exists() or (out / "images").exists():
        if not overwrite:
            raise FileExistsError(f"{out} already holds a capture; pass overwrite=True to replace it")
        for sub in ("images", "masks", "gt", "template"):
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)
        for f in ("capture.json", "calibration.json", "splits.json", "motion.npz"):
            (out / f).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    if cfg.supersample < 1 or cfg.num_frames < 2 or cfg.num_cams < 1:
        raise ValueError(
            f"need supersample >= 1, num_frames >= 2, num_cams >= 1; got {cfg.supersample}, "
            f"{cfg.num_frames}, {cfg.num_cams}"
        )

    template, rig = build_anny_body(Path(anny_cache_dir), decimate_to=cfg.decimate_to, seed=cfg.body_seed)
    motion = load_motion(cfg, rig)
    F = cfg.num_frames
    verts = pose_vertices(template, rig, motion.pose, motion.root_rotation, motion.root_translation)

    # Cameras framed on the motion: centre and horizontal reach of the posed body.
    xz = verts[..., [0, 2]].reshape(-1, 2)
    center = 0.5 * (xz.min(0) + xz.max(0))
    reach = float(np.linalg.norm(xz - center, axis=1).max())
    body_height = float(template.vertices[:, 1].max() - template.vertices[:, 1].min())
    y_range = (float(verts[..., 1].min()), float(verts[..., 1].max()))
    cameras = make_dome(
        cfg.num_cams,
        cfg.width,
        cfg.height,
        body_height,
        cfg.seed,
        cfg.distortion,
        center=center,
        radius=cfg.cam_radius,
        reach=reach,
        y_range=y_range,
    )
    cameras |= special_cameras(cfg.special_cameras, cfg.width, cfg.height, body_height, center=center, reach=reach)
    for key, name in (("occluded_camera", cfg.occluded_camera), ("corrupted_camera", cfg.corrupted_camera)):
        if name is not None and name not in cameras:
            raise ValueError(f"{key} {name!r} is not a camera of this dome ({sorted(cameras)})")
    occluders: dict[str, list[TriMesh]] = {}
    if cfg.occluded_camera is not None:
        # A box 60 % of the way from the camera to the hips: hides the hips/thighs in that view only.
        c = cameras[cfg.occluded_camera].center
        tgt = np.array([center[0], 0.5 * body_height, center[1]])
        occluders[cfg.occluded_camera] = [box_mesh(c + 0.6 * (tgt - c), (0.3, 0.3, 0.3), (0.55, 0.55, 0.5))]

    splits = default_splits(cfg, cameras)
    train = np.asarray(splits["train"].frames)
    slot, pname = coupling_slot(rig, motion.pose, train, cfg.coupled_param)
    joints = (
        pose_joint_positions(rig, motion.pose, motion.root_rotation, motion.root_translation)
        if cfg.appearance.motion_effects
        else None
    )
    app = AppearanceModel(
        template,
        F,
        train_frames=train,
        coupling_signal=motion.pose[:, slot],
        rig=rig,
        seed=cfg.seed,
        tex_size=cfg.tex_size,
        fps=cfg.fps,
        config=cfg.appearance,
        joint_positions=joints,
        joint_names=[j.name for j in rig.joints],
    )
    motion = Motion(motion.pose, motion.root_rotation, motion.root_translation, app.face_embedding)
    rng = np.random.default_rng([cfg.seed, 31])
    corrupted: list[int] = []
    if cfg.corrupted_camera is not None:
        n = int(round(cfg.corrupted_fraction * F))
        corrupted = sorted(int(f) for f in rng.choice(F, n, replace=False))

    # Static files first (capture.json etc. last).
    save_template(template, out / "template")
    rig.save(out / "template" / "rig.json")
    motion.save(out / "motion.npz")
    gt = out / "gt"
    atomic_write_json(gt / "config.json", cfg.to_json())
    atomic_save_npz(
        gt / "regions.npz",
        covered=app.uv.covered.astype(np.uint8) * 255,
        **{k: np.rint(np.clip(v, 0, 1) * 255).astype(np.uint8) for k, v in app.regions.items()},
    )

    if app.motion_levels:
        names = list(app.motion_levels)
        levels = np.stack([app.motion_levels[k] for k in names], 1).astype(np.float32)  # [F, E]
        signals = np.stack([app.motion_signals[k] for k in names], 1).astype(np.float32)
        atomic_save_npz(gt / "motion_states.npz", names=np.array(names), levels=levels, signals=signals)
        atomic_write_json(
            gt / "fairness.json",
            history_fairness(motion, levels, train, np.asarray(splits["test"].frames), joints=joints),
        )

    job = _RenderJob(
        out,
        template.faces,
        template.corner_uvs,
        verts,
        cameras,
        app,
        cfg.supersample,
        Shading() if cfg.shading else None,
        tuple(cfg.background),
        occluders,
        cfg.corrupted_camera,
        frozenset(corrupted),
        cfg.seed,
    )
    results = _render_all(job, F, cfg.workers, progress)

    views = results[0]["views"]
    atomic_save_npz(gt / "texel_views.npz", count=views.reshape(cfg.tex_size, cfg.tex_size), frame=np.int64(0))
    atomic_write_json(
        gt / "states.json",
        {
            "format": GT_FORMAT,
            "version": GT_VERSION,
            "preset": cfg.preset,
            "seed": cfg.seed,
            "texture_size": cfg.tex_size,
            "textures": "gt/textures/{frame:08d}.png: UNSHADED albedo; images are albedo x shading "
            f"({'ambient 0.65 + 0.35 Lambert' if cfg.shading else 'none'})",
            "coupling": {
                "garment": "trousers",
                "state": "trouser_fold",
                "param": pname,
                "slot": slot,
                "threshold": app.coupling_threshold,
                "states_low_high": list(app.coupling_states),
            },
            "coupled_frames": [int(f) for f in np.flatnonzero(app.coupled)],
            "corrupted": {"camera": cfg.corrupted_camera, "frames": corrupted},
            "occluded_camera": cfg.occluded_camera,
            "special_cameras": list(cfg.special_cameras),
            "camera_kinds": {n: (n if n in cfg.special_cameras else camera_kind(n)) for n in cameras},
            "dome": {
                "center_xz": [float(x) for x in center],
                "reach": reach,
                "y_range": list(y_range),
                "body_height": body_height,
            },
            "mean_color_frame0": results[0]["mean_color"],
            "motion_effects": {k: {"constants": app.motion_constants[k]} for k in app.motion_levels},
            "frames": app.states(),
        },
    )
    write_capture_metadata(out, cfg.fps, F, cameras, splits)
    return out


def _render_all(job: _RenderJob, num_frames: int, workers: int, progress: bool) -> dict[int, dict]:
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    n = workers if workers > 0 else (os.cpu_count() or 1)
    if workers <= 0:
        # Worker start-up (spawn + imports, ~3 s) only pays off for big jobs.
        rays = sum(c.width * c.height for c in job.cameras.values()) * job.supersample**2 * num_frames
        n = n if rays > 3e7 else 1
    n = max(1, min(n, num_frames))
    results: dict[int, dict] = {}
    cols = (
        TextColumn("[bold]render[/]"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*cols, disable=not progress) as bar:
        task = bar.add_task("frames", total=num_frames)
        if n == 1:
            _init_worker(job)
            for f in range(num_frames):
                results[f] = _render_frame(f)
                bar.advance(task)
        else:
            # spawn, not fork: the parent has live torch/Embree thread pools that fork cannot copy safely.
            with ProcessPoolExecutor(
                n, mp_context=get_context("spawn"), initializer=_init_worker, initargs=(job,)
            ) as pool:
                for r in pool.map(_render_frame, range(num_frames), chunksize=1):
                    results[r["frame"]] = r
                    bar.advance(task)
    return results


# --------------------------------------------------------------------------- CLI
@dataclass
class MakeArgs:
    out: Path
    """Capture directory to write."""
    config: SynthConfig
    """What to build (any field of the chosen preset can be overridden, e.g. ``--config.seed 3``)."""
    anny_cache: Path | None = None
    """Anny model-data cache directory (default: $ANNY_CACHE_DIR, else ~/.cache/gsavatar/anny)."""
    overwrite: bool = False
    """Replace an existing capture in ``out``."""
    force_out: bool = False
    """Write into a non-empty ``out`` that holds no capture (refused otherwise, so a user's files are never
    overwritten)."""


def main() -> int:
    """``python -m gsavatar.synth.make {tiny,small,hard} --out DIR [--config.FIELD VALUE ...]``"""
    import time

    import tyro

    args = tyro.extras.overridable_config_cli(
        {
            name: (PRESET_HELP[name], MakeArgs(out=Path(f"captures/synth_{name}"), config=cfg))
            for name, cfg in PRESETS.items()
        }
    )
    cfg = args.config
    cache = args.anny_cache or default_anny_cache()

    def run() -> None:
        claim_output_dir(args.out, "capture", args.force_out, "--force-out")
        t0 = time.perf_counter()
        make_capture(cfg, args.out, cache, progress=True, overwrite=args.overwrite)
        print(
            f"wrote {args.out} ({cfg.preset}: {cfg.num_cams + len(cfg.special_cameras)} cameras x {cfg.num_frames} "
            f"frames) in {time.perf_counter() - t0:.1f} s"
        )

    return run_reporting_errors(run)


if __name__ == "__main__":
    raise SystemExit(main())
