"""Stage implementations behind the ``avatar-prep`` subcommands (thin glue over the math modules)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from gsavatar.data_schema import load_capture
from gsavatar.data_schema.dataset import read_dataset_json, stage_complete
from gsavatar.prep.common import StageArgs, open_capture, run_frame_stage, run_single_file_stage
from gsavatar.prep.inputs import frame_inputs, metadata_inputs, upstream_inputs
from gsavatar.utils.io import read_npz
from gsavatar.utils.paths import output_path

# Capture files each stage reads (fingerprinted; a change re-runs the stage). ``template/`` = every file in it.
POSE_TEMPLATE_INPUTS = ("capture.json", "motion.npz", "template/")
UV_ATLAS_INPUTS = ("template/",)
PROJECT_UV_INPUTS = ("capture.json", "calibration.json", "splits.json", "template/")  # + images, masks, upstream
FIT_PCA_INPUTS = ("motion.npz", "splits.json", "template/rig.json")
SAMPLE_POINTS_INPUTS = ("template/",)  # automatic counts come from calibration.json but are resolved into the config
LOCALIZE_INPUTS = ("template/",)  # + sample-points


# --------------------------------------------------------------------------- pose-template
def _pose_shard(capture_dir: str, frames: list[int]) -> dict[str, np.ndarray]:
    from gsavatar.prep.pose_template import pose_vertices

    return {"vertices": pose_vertices(load_capture(capture_dir, check_files=False), frames)}


def pose_template(args: StageArgs) -> bool:
    cap = open_capture(args)
    frames = list(range(cap.num_frames))
    return run_frame_stage("pose-template", args, {"num_vertices": int(len(cap.template.vertices))}, frames,
                           functools.partial(_pose_shard, str(args.capture)),
                           metadata_inputs(cap.root, POSE_TEMPLATE_INPUTS))


# --------------------------------------------------------------------------- uv-atlas
def auto_tex_size(cap) -> int:
    """Texture a capture's images can fill: a power of two about twice the largest image side
    (a texel per half pixel), clamped to [256, 1024] (1024 = the paper's size)."""
    side = max(max(c.width, c.height) for c in cap.cameras.values())
    return int(np.clip(2 ** int(np.ceil(np.log2(2 * side))), 256, 1024))


def resolve_tex_size(cfg, cap):
    """``cfg`` (a ProjectConfig) with ``tex_size`` 0 replaced by :func:`auto_tex_size`."""
    import dataclasses

    if cfg.tex_size:
        return cfg
    size = auto_tex_size(cap)
    print(f"[project-uv] texture size {size}x{size} (derived from the capture's images)")
    return dataclasses.replace(cfg, tex_size=size)


def atlas_config(tex_size: int, gutter_px: float) -> dict:
    return {"tex_size": int(tex_size), "gutter_px": float(gutter_px)}


def uv_atlas(args: StageArgs, tex_size: int, gutter_px: float = 1.0) -> bool:
    from gsavatar.prep.uv_atlas import build_texel_map, ensure_uvs
    from gsavatar.utils.io import atomic_save_npz

    cap = open_capture(args)
    root = Path(args.out)

    def produce() -> list[Path]:
        t = ensure_uvs(cap.template, cache_dir=root / "uv_atlas" / "xatlas_cache")
        tm = build_texel_map(t, size=tex_size, gutter=gutter_px)
        path = root / "uv_atlas" / "atlas.npz"
        # face_uv_mask belongs to the template's own UV layout; after an xatlas unwrap there is none.
        face_mask = t.face_uv_mask if t.face_uv_mask is not None else np.zeros((1, 1), bool)
        atomic_save_npz(path, face=tm.face, bary=tm.bary, interior=tm.interior, size=np.int64(tm.size),
                        uvs=t.uvs, face_uvs=t.face_uvs, face_uv_mask=face_mask)
        print(f"[uv-atlas] {tex_size}x{tex_size}: {tm.valid.mean():.1%} of texels on the surface "
              f"({'template UVs' if cap.template.uvs is not None else 'xatlas unwrap'})")
        return [path]

    return run_single_file_stage("uv-atlas", args, atlas_config(tex_size, gutter_px), produce,
                                 metadata_inputs(cap.root, UV_ATLAS_INPUTS))


def load_atlas(root: Path):
    """The texel map and UVs written by ``uv-atlas``."""
    from gsavatar.data_schema.dataset import stage_path
    from gsavatar.prep.uv_atlas import TexelMap

    z = read_npz(stage_path(Path(root), "uv-atlas", "atlas.npz"), keys=("face", "bary", "size", "interior", "uvs", "face_uvs"))
    return TexelMap(z["face"], z["bary"], int(z["size"]), z["interior"]), z["uvs"], z["face_uvs"]


def load_atlas_face_mask(root: Path) -> np.ndarray | None:
    """Face region in the atlas' UV layout (None after an xatlas unwrap or without a mask).  # [h, w] bool"""
    from gsavatar.data_schema.dataset import stage_path

    m = read_npz(stage_path(Path(root), "uv-atlas", "atlas.npz"), keys=("face_uv_mask",))["face_uv_mask"]
    return m if m.any() else None


# --------------------------------------------------------------------------- project-uv
def _project_shard(capture_dir: str, dataset: str, cfg_json: dict, cams: list[str], frames: list[int]) -> dict[str, np.ndarray]:
    from gsavatar.data_schema.dataset import ShardReader, stage_dir
    from gsavatar.prep.project_uv import ProjectConfig, UVProjector, iter_frame_views

    cap = load_capture(capture_dir)
    tm, _, _ = load_atlas(Path(dataset))
    cfg = ProjectConfig(**{**cfg_json, "band": tuple(cfg_json["band"])})
    proj = UVProjector(cap.template.faces, tm, cfg, load_atlas_face_mask(Path(dataset)))
    posed = ShardReader(stage_dir(Path(dataset), "pose-template"))
    tex, cnt, seen = [], [], []
    for f in frames:
        out = proj.project(posed.get(f)["vertices"], iter_frame_views(cap, f, cams), frame=f)
        tex.append(out.texture.astype(np.float16))
        cnt.append(out.count)
        seen.append(out.seen)
    return {"texture": np.stack(tex), "count": np.stack(cnt), "seen": np.stack(seen)}


def check_cameras_see_body(cap, cams: list[str], max_frames: int = 8) -> None:
    """Refuse a calibration under which none of ``cams`` sees the posed body in any of up to
    ``max_frames`` evenly spaced frames (every camera behind or pointed away from it, e.g. R, T given
    camera-to-world): the textures would be empty. Single blind cameras are allowed (a warning)."""
    from gsavatar.data_schema import SchemaError
    from gsavatar.prep.pose_template import pose_vertices
    from gsavatar.prep.project_uv import cameras_seeing

    frames = sorted({int(f) for f in np.linspace(0, cap.num_frames - 1, min(max_frames, cap.num_frames)).round()})
    verts = pose_vertices(cap, frames).reshape(-1, 3)  # [n*V, 3] world, metres
    seeing = cameras_seeing(verts, [cap.cameras[c] for c in cams])
    if not seeing:
        raise SchemaError(cap.root / "calibration.json", "R/T",
                          f"the body is behind or outside every projected camera ({', '.join(cams)}) in frames {frames}: "
                          "check that R, T map world to camera (x_cam = R x_world + T, +z forward)")
    blind = [c for c in cams if c not in seeing]
    if blind:
        print(f"[project-uv] warning: cameras {blind} see no part of the body in frames {frames}")


def project_uv(args: StageArgs, cfg, cameras: str = "train") -> bool:
    """``cameras``: ``train`` (default: held-out views never leak into textures) or ``all``."""
    from gsavatar.prep.common import stage_config

    cap = open_capture(args)
    cfg = resolve_tex_size(cfg, cap)
    cams = sorted(cap.splits["train"].cameras) if cameras == "train" else sorted(cap.cameras)
    check_cameras_see_body(cap, cams)
    from gsavatar.prep.project_uv import check_mask_coverage

    check_mask_coverage(cap, cams)
    pose_template(args)
    uv_atlas(args, cfg.tex_size, cfg.gutter_px)
    config = {**stage_config(cfg), "cameras": cams}
    cfg_json = stage_config(cfg)
    inputs = {**metadata_inputs(cap.root, PROJECT_UV_INPUTS),
              **upstream_inputs(Path(args.out), ("pose-template", "uv-atlas"))}
    return run_frame_stage("project-uv", args, config, list(range(cap.num_frames)),
                           functools.partial(_project_shard, str(args.capture), str(args.out), cfg_json, cams),
                           inputs, functools.partial(frame_inputs, cap, cams=cams))


# --------------------------------------------------------------------------- fit-pca
def fit_pca(args: StageArgs, n_components: int = 5, global_components: int = 20, clamp_sigma: float = 2.0) -> bool:
    from gsavatar.prep.pca import fit_pose_pca

    cap = open_capture(args)
    root = Path(args.out)
    config = {"n_components": n_components, "global_components": global_components, "clamp_sigma": clamp_sigma,
              "train_frames": len(cap.splits["train"].frames)}

    def produce() -> list[Path]:
        poses = cap.motion.pose[cap.splits["train"].frames]
        out = []
        for mode, k in (("local", n_components), ("global", global_components)):
            p = fit_pose_pca(poses, cap.rig, n_components=k, mode=mode, clamp_sigma=clamp_sigma)
            path = root / "fit_pca" / f"{mode}.npz"
            p.save(path)
            out.append(path)
            if mode == "local":
                print(f"[fit-pca] local components per group: {p.components_per_group()}")
        return out

    return run_single_file_stage("fit-pca", args, config, produce, metadata_inputs(cap.root, FIT_PCA_INPUTS))


# --------------------------------------------------------------------------- sample-points
def auto_point_counts(cap) -> dict[str, int]:
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


def sample_points(args: StageArgs, anchors: int = 0, control: int = 0, gaussians: int = 0, seed: int = 0) -> bool:
    from gsavatar.prep.sample_points import build_hierarchy

    cap = open_capture(args)
    root = Path(args.out)
    auto = auto_point_counts(cap)
    counts = {"anchors": anchors or auto["anchors"], "control": control or auto["control"],
              "gaussians": gaussians or auto["gaussians"]}
    config = {**counts, "seed": seed}

    def produce() -> list[Path]:
        chosen = ", ".join(f"{k} {v}" + (" (auto)" if not {"anchors": anchors, "control": control, "gaussians": gaussians}[k] else "")
                           for k, v in counts.items())
        print(f"[sample-points] {chosen}")
        h = build_hierarchy(cap.template, counts["anchors"], counts["control"], counts["gaussians"], seed=seed)
        path = root / "sample_points" / "hierarchy.npz"
        h.save(path)
        return [path]

    return run_single_file_stage("sample-points", args, config, produce,
                                 metadata_inputs(cap.root, SAMPLE_POINTS_INPUTS))


# --------------------------------------------------------------------------- localize
def localize(args: StageArgs, ancestor_levels: int = 1, k_neighbors: int = 6, figure_param: str = "Neck.ry",
             figures: bool = True) -> bool:
    from gsavatar.data_schema.dataset import stage_path
    from gsavatar.data_schema.hierarchy import Hierarchy
    from gsavatar.prep.localize import build_localization

    cap = open_capture(args)
    root = Path(args.out)
    if not stage_complete(root, "sample-points", inputs=metadata_inputs(cap.root, SAMPLE_POINTS_INPUTS)):
        # any recorded counts are fine: a stale record is recomputed with its own counts, a missing one with the defaults
        rec = read_dataset_json(root)["stages"].get("sample-points") or {}
        keep = {k: v for k, v in (rec.get("config") or {}).items() if k in ("anchors", "control", "gaussians", "seed")}
        sample_points(args, **keep)
    config = {"ancestor_levels": ancestor_levels, "k_neighbors": k_neighbors, "figure_param": figure_param, "figures": figures}

    def produce() -> list[Path]:
        h = Hierarchy.load(stage_path(root, "sample-points", "hierarchy.npz"))
        masks = build_localization(h, cap.rig, cap.template.face_uv_mask, ancestor_levels=ancestor_levels,
                                   k_neighbors=k_neighbors, template=cap.template)
        path = root / "localize" / "masks.npz"
        masks.save(path)
        files = [path]
        active = masks.pose.mean()
        print(f"[localize] {masks.pose.shape[0]} anchors x {masks.pose.shape[1]} pose slots, {active:.1%} active; "
              f"{int(masks.face.sum())} face anchors")
        if figures:
            from gsavatar.prep.figures import render_hierarchy_figure, render_influence_figure

            param = figure_param if figure_param in [p.name for p in cap.rig.params] else cap.rig.params[0].name
            files.append(Path(render_hierarchy_figure(cap.template, h, root / "localize" / "hierarchy.png")))
            files.append(Path(render_influence_figure(cap.template, h, masks, cap.rig,
                                                      output_path(root, "localize", f"influence_{param}.png"), param=param)))
        return files

    inputs = {**metadata_inputs(cap.root, LOCALIZE_INPUTS), **upstream_inputs(root, ("sample-points",))}
    return run_single_file_stage("localize", args, config, produce, inputs)
