"""Stage run functions behind the ``avatar-prep`` subcommands (thin glue over the math modules).

Each takes ``(args, capture, config, inputs)``: the command's common arguments, the loaded capture, the
stage's config (:mod:`gsavatar.prep.configs`; ``0 = derived`` fields resolved here) and the fingerprint
of what it reads (built from the stage table, :mod:`gsavatar.prep.table`). None calls another stage: the
table says which stages run first, and :func:`gsavatar.prep.table.run_stages` runs them.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from gsavatar.data_schema import Capture, SchemaError, load_capture
from gsavatar.data_schema.dataset import ShardReader, read_dataset_json, stage_dir, stage_path
from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.prep.common import StageArgs, run_frame_stage, run_single_file_stage, stage_config
from gsavatar.prep.configs import (
    FitPcaConfig,
    LocalizeConfig,
    PoseTemplateConfig,
    ProjectConfig,
    ProjectUvConfig,
    SamplePointsConfig,
    UvAtlasConfig,
)
from gsavatar.prep.figures import render_hierarchy_figure, render_influence_figure
from gsavatar.prep.inputs import frame_inputs
from gsavatar.prep.localize import build_localization
from gsavatar.prep.pca import fit_pose_pca
from gsavatar.prep.project_uv import (
    UVProjector,
    cameras_seeing,
    check_mask_coverage,
    prefetched_frame_views,
    preflight_frames,
)
from gsavatar.prep.sample_points import build_hierarchy
from gsavatar.prep.uv_atlas import TexelMap, build_texel_map, ensure_uvs
from gsavatar.utils.io import atomic_save_npz, read_npz
from gsavatar.utils.paths import output_path


# --------------------------------------------------------------------------- pose-template
def _pose_shard(capture_dir: str, frames: list[int]) -> dict[str, np.ndarray]:
    # local: pose_template imports torch (geometry.lbs); prep.stages and prep.report load without it
    from gsavatar.prep.pose_template import pose_vertices

    return {"vertices": pose_vertices(load_capture(capture_dir, check_files=False), frames)}


def pose_template(args: StageArgs, cap: Capture, cfg: PoseTemplateConfig, inputs: dict[str, str]) -> bool:
    frames = list(range(cap.num_frames))
    return run_frame_stage(
        "pose-template",
        args,
        {"num_vertices": int(len(cap.template.vertices))},
        frames,
        functools.partial(_pose_shard, str(args.capture)),
        inputs,
    )


# --------------------------------------------------------------------------- uv-atlas
def auto_tex_size(cap: Capture) -> int:
    """Texture a capture's images can fill: a power of two about twice the largest image side
    (a texel per half pixel), clamped to [256, 1024] (1024 = the paper's size)."""
    side = max(max(c.width, c.height) for c in cap.cameras.values())
    return int(np.clip(2 ** int(np.ceil(np.log2(2 * side))), 256, 1024))


def resolve_tex_size(cfg: ProjectConfig, cap: Capture) -> ProjectConfig:
    """``cfg`` with ``tex_size`` None (derived) replaced by :func:`auto_tex_size`."""
    if cfg.tex_size is not None:
        return cfg
    size = auto_tex_size(cap)
    print(f"[project-uv] texture size {size}x{size} (derived from the capture's images)")
    return dataclasses.replace(cfg, tex_size=size)


def atlas_config(tex_size: int, gutter_px: float) -> dict:
    return {"tex_size": int(tex_size), "gutter_px": float(gutter_px)}


def atlas_for_projection(cfg: ProjectUvConfig) -> UvAtlasConfig:
    """The atlas project-uv reads: its texture size (None = derived the same way) and seam gutter."""
    return UvAtlasConfig(tex_size=cfg.project.tex_size, gutter_px=cfg.project.gutter_px)


def uv_atlas(args: StageArgs, cap: Capture, cfg: UvAtlasConfig, inputs: dict[str, str]) -> bool:
    root = Path(args.out)
    tex_size = auto_tex_size(cap) if cfg.tex_size is None else cfg.tex_size

    def produce() -> list[Path]:
        t = ensure_uvs(cap.template, cache_dir=root / "uv_atlas" / "xatlas_cache")
        tm = build_texel_map(t, size=tex_size, gutter=cfg.gutter_px)
        path = root / "uv_atlas" / "atlas.npz"
        # face_uv_mask belongs to the template's own UV layout; after an xatlas unwrap there is none.
        face_mask = t.face_uv_mask if t.face_uv_mask is not None else np.zeros((1, 1), bool)
        atomic_save_npz(
            path,
            face=tm.face,
            bary=tm.bary,
            interior=tm.interior,
            size=np.int64(tm.size),
            uvs=t.uvs,
            face_uvs=t.face_uvs,
            face_uv_mask=face_mask,
        )
        print(
            f"[uv-atlas] {tex_size}x{tex_size}: {tm.valid.mean():.1%} of texels on the surface "
            f"({'template UVs' if cap.template.uvs is not None else 'xatlas unwrap'})"
        )
        return [path]

    return run_single_file_stage("uv-atlas", args, atlas_config(tex_size, cfg.gutter_px), produce, inputs)


def load_atlas(root: Path):
    """The texel map and UVs written by ``uv-atlas``."""
    z = read_npz(
        stage_path(Path(root), "uv-atlas", "atlas.npz"), keys=("face", "bary", "size", "interior", "uvs", "face_uvs")
    )
    return TexelMap(z["face"], z["bary"], int(z["size"]), z["interior"]), z["uvs"], z["face_uvs"]


def load_atlas_face_mask(root: Path) -> np.ndarray | None:
    """Face region in the atlas' UV layout (None after an xatlas unwrap or without a mask).  # [h, w] bool"""
    m = read_npz(stage_path(Path(root), "uv-atlas", "atlas.npz"), keys=("face_uv_mask",))["face_uv_mask"]
    return m if m.any() else None


# --------------------------------------------------------------------------- project-uv
def _project_shard(
    capture_dir: str, dataset: str, cfg_json: dict, cams: list[str], frames: list[int]
) -> dict[str, np.ndarray]:
    cap = load_capture(capture_dir)
    tm, _, _ = load_atlas(Path(dataset))
    cfg = ProjectConfig(**{**cfg_json, "band": tuple(cfg_json["band"])})
    proj = UVProjector(cap.template.faces, tm, cfg, load_atlas_face_mask(Path(dataset)))
    posed = ShardReader(stage_dir(Path(dataset), "pose-template"))
    tex, cnt, seen = [], [], []
    for f, views in prefetched_frame_views(cap, frames, cams, uint8=True):  # the next frame is read meanwhile
        out = proj.project(posed.get(f)["vertices"], views, frame=f)
        tex.append(out.texture.astype(np.float16))
        cnt.append(out.count)
        seen.append(out.seen)
    return {"texture": np.stack(tex), "count": np.stack(cnt), "seen": np.stack(seen)}


def projected_cameras(cap: Capture, cameras: str) -> list[str]:
    """``cameras``: ``train`` (held-out views never leak into textures) or ``all``."""
    return sorted(cap.splits["train"].cameras) if cameras == "train" else sorted(cap.cameras)


def check_cameras_see_body(cap: Capture, cams: list[str], max_frames: int = 8) -> None:
    """Refuse a calibration under which none of ``cams`` sees the posed body in any of up to
    ``max_frames`` evenly spaced frames (every camera behind or pointed away from it, e.g. R, T given
    camera-to-world): the textures would be empty. Single blind cameras are allowed (a warning)."""
    # local: pose_template imports torch (geometry.lbs); prep.stages and prep.report load without it
    from gsavatar.prep.pose_template import pose_vertices

    frames = preflight_frames(cap.num_frames, max_frames)
    verts = pose_vertices(cap, frames).reshape(-1, 3)  # [n*V, 3] world, metres
    seeing = cameras_seeing(verts, [cap.cameras[c] for c in cams])
    if not seeing:
        raise SchemaError(
            cap.root / "calibration.json",
            "R/T",
            f"the body is behind or outside every projected camera ({', '.join(cams)}) in frames {frames}: "
            "check that R, T map world to camera (x_cam = R x_world + T, +z forward)",
        )
    blind = [c for c in cams if c not in seeing]
    if blind:
        print(f"[project-uv] warning: cameras {blind} see no part of the body in frames {frames}")


def check_project_uv(cap: Capture, cfg: ProjectUvConfig) -> None:
    """Refuse, before any stage runs, a capture whose projected views would give empty textures."""
    cams = projected_cameras(cap, cfg.cameras)
    check_cameras_see_body(cap, cams)
    check_mask_coverage(cap, cams)


def recorded_before_visibility(root: Path) -> bool:
    """Whether ``root`` holds project-uv output recorded before ``ProjectConfig.visibility`` existed (ray cast)."""
    try:
        rec = read_dataset_json(root)["stages"].get("project-uv")
    except SchemaError:
        return False
    return isinstance(rec, dict) and isinstance(rec.get("config"), dict) and "visibility" not in rec["config"]


def project_uv(args: StageArgs, cap: Capture, cfg: ProjectUvConfig, inputs: dict[str, str]) -> bool:
    proj = resolve_tex_size(cfg.project, cap)
    cams = projected_cameras(cap, cfg.cameras)
    record = cfg_json = stage_config(proj)
    if not args.force and recorded_before_visibility(Path(args.out)):
        # Textures of an older gsavatar were ray cast. Recomputing them with the z-buffer would change the
        # dataset's content id and strand every run trained on it, so the dataset keeps its method (also for
        # frames still to do); --force recomputes everything with the configured one.
        print(
            "[project-uv] dataset projected before the z-buffer existed: keeping its ray-cast visibility "
            "(--force recomputes with the z-buffer)"
        )
        cfg_json = {**cfg_json, "visibility": "rays"}
        record = {k: v for k, v in cfg_json.items() if k != "visibility"}
    return run_frame_stage(
        "project-uv",
        args,
        {**record, "cameras": cams},
        list(range(cap.num_frames)),
        functools.partial(_project_shard, str(args.capture), str(args.out), cfg_json, cams),
        inputs,
        functools.partial(frame_inputs, cap, cams=cams),
    )


# --------------------------------------------------------------------------- fit-pca
def fit_pca(args: StageArgs, cap: Capture, cfg: FitPcaConfig, inputs: dict[str, str]) -> bool:
    root = Path(args.out)
    config = {
        "n_components": cfg.n_components,
        "global_components": cfg.global_components,
        "clamp_sigma": cfg.clamp_sigma,
        "train_frames": len(cap.splits["train"].frames),
    }

    def produce() -> list[Path]:
        poses = cap.motion.pose[cap.splits["train"].frames]
        out = []
        for mode, k in (("local", cfg.n_components), ("global", cfg.global_components)):
            p = fit_pose_pca(poses, cap.rig, n_components=k, mode=mode, clamp_sigma=cfg.clamp_sigma)
            path = root / "fit_pca" / f"{mode}.npz"
            p.save(path)
            out.append(path)
            if mode == "local":
                print(f"[fit-pca] local components per group: {p.components_per_group()}")
        return out

    return run_single_file_stage("fit-pca", args, config, produce, inputs)


# --------------------------------------------------------------------------- sample-points
def auto_point_counts(cap: Capture) -> dict[str, int]:
    """Point counts a scene needs: Gaussians scale with the foreground pixels a view can resolve.

    About 2 Gaussians per foreground pixel of the largest view (a full-body view covers about
    1/3 of its image; the dome sees roughly twice that surface), capped at the paper's
    300 / 10k / 200k: 128x128 views -> ~11k Gaussians, 1152x1332 -> 200k.
    """
    px = max(c.width * c.height for c in cap.cameras.values())
    n_g = int(np.clip(2 * px / 3, 5_000, 200_000))
    n_c = int(np.clip(n_g // 20, 500, 10_000))
    n_a = int(np.clip(n_c // 33, 24, 300))
    return {"anchors": n_a, "control": n_c, "gaussians": n_g}


def sample_points(args: StageArgs, cap: Capture, cfg: SamplePointsConfig, inputs: dict[str, str]) -> bool:
    root = Path(args.out)
    given = {"anchors": cfg.anchors, "control": cfg.control, "gaussians": cfg.gaussians}
    auto = auto_point_counts(cap)
    counts = {k: auto[k] if v is None else v for k, v in given.items()}

    def produce() -> list[Path]:
        print(
            "[sample-points] "
            + ", ".join(f"{k} {v}" + ("" if given[k] is not None else " (auto)") for k, v in counts.items())
        )
        # A template without UVs gets uv-atlas' unwrap (the same cached xatlas call, a function of the template
        # alone): the points need UVs in the layout the textures are projected into.
        template = ensure_uvs(cap.template, cache_dir=root / "uv_atlas" / "xatlas_cache")
        h = build_hierarchy(template, counts["anchors"], counts["control"], counts["gaussians"], seed=cfg.seed)
        path = root / "sample_points" / "hierarchy.npz"
        h.save(path)
        return [path]

    return run_single_file_stage("sample-points", args, {**counts, "seed": cfg.seed}, produce, inputs)


# --------------------------------------------------------------------------- localize
def localize(args: StageArgs, cap: Capture, cfg: LocalizeConfig, inputs: dict[str, str]) -> bool:
    root = Path(args.out)

    def produce() -> list[Path]:
        h = Hierarchy.load(stage_path(root, "sample-points", "hierarchy.npz"))
        masks = build_localization(
            h,
            cap.rig,
            cap.template.face_uv_mask,
            ancestor_levels=cfg.ancestor_levels,
            k_neighbors=cfg.k_neighbors,
            template=cap.template,
        )
        path = root / "localize" / "masks.npz"
        masks.save(path)
        files = [path]
        active = masks.pose.mean()
        print(
            f"[localize] {masks.pose.shape[0]} anchors x {masks.pose.shape[1]} pose slots, {active:.1%} active; "
            f"{int(masks.face.sum())} face anchors"
        )
        if cfg.figures:
            names = [p.name for p in cap.rig.params]
            param = cfg.figure_param if cfg.figure_param in names else names[0]
            files.append(Path(render_hierarchy_figure(cap.template, h, root / "localize" / "hierarchy.png")))
            files.append(
                Path(
                    render_influence_figure(
                        cap.template,
                        h,
                        masks,
                        cap.rig,
                        output_path(root, "localize", f"influence_{param}.png"),
                        param=param,
                    )
                )
            )
        return files

    config = {
        "ancestor_levels": cfg.ancestor_levels,
        "k_neighbors": cfg.k_neighbors,
        "figure_param": cfg.figure_param,
        "figures": cfg.figures,
    }
    return run_single_file_stage("localize", args, config, produce, inputs)
