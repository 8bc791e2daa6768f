"""Benchmark the per-frame UV texel projection (``gsavatar.prep.project_uv``).

Not a test. For each texture size, visibility path (``--visibility``: the compiled
``zbuffer`` path and/or the numpy + open3d ``rays`` reference) and thread count
(``--threads``: numba threads of the z-buffer kernels) it reports seconds per frame of
:meth:`UVProjector.project` (images already decoded), the decode floor of that frame
(raw ``cv2.imread`` of its images + masks, re-measured right before each projection so
both see the same machine load) and their ratio, the time through gsavatar's readers,
texels/s, and the error of the fused texture against the ground-truth texture (PSNR on
texels seen by >= 2 views; ``median_band`` and, for comparison, ``mean`` fusion).
Prints a markdown table, where one frame's projection goes (``--no-parts`` skips it), and (unless
``--no-stage-loop``) the stage's own loop at the largest size
with the most threads: read a frame through gsavatar's readers and project it, frame after frame, with
and without the next frame read in a background thread (``prefetched_frame_views``).

Inputs:

- ``--capture DIR``: a synthetic capture (``gsavatar.synth``) with
  ``gt/textures/{frame:08d}.png``; the template must have UVs. Posed vertices come
  from LBS of ``motion.npz`` (:func:`gsavatar.prep.pose_template.pose_vertices`).
  Note: synthetic images are albedo x shading while ``gt/textures`` is the unshaded
  albedo, so the PSNR there is bounded by the shading, not by the projection.
- no ``--capture``: a built-in scene: a body-like pair of ellipsoids (xatlas-unwrapped,
  ~25k triangles, self-occluding) with an analytic texture of the rest position,
  rendered (exact, unshaded) into ``--views`` 8-bit PNG views on a ring, written to a
  temp capture-style folder so the I/O floor is real PNG decoding.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_project_uv.py
    PYTHONPATH=src .venv/bin/python benchmarks/bench_project_uv.py --capture /data/synth_a --frames 0 10
    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python benchmarks/bench_project_uv.py --thuman4 --sizes 512 1024 \
        --threads 1 2 --visibility zbuffer rays --no-mean --frames 0 1 2 3
"""

from __future__ import annotations

import argparse
import math
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gsavatar.data_schema.capture import Camera, Capture
from gsavatar.geometry.camera import look_at, pixel_rays
from gsavatar.prep.project_uv import ProjectConfig, UVProjector, load_frame_views, prefetched_frame_views
from gsavatar.prep.uv_atlas import build_texel_map, ensure_uvs
from gsavatar.geometry.primitives import icosphere


# --------------------------------------------------------------------------- built-in scene
def _albedo(p: np.ndarray) -> np.ndarray:
    """Analytic texture of the rest position p [..., 3] (metres) -> RGB in [0.15, 0.85]."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    r = 0.5 + 0.3 * np.sin(2 * np.pi * (3.0 * y + 1.5 * x))
    g = 0.5 + 0.25 * np.cos(2 * np.pi * (4.0 * z + 2.0 * y))
    b = 0.5 + 0.2 * np.sin(2 * np.pi * (2.5 * x - 2.0 * z + y))
    return np.stack([r, g, b], -1)


def builtin_scene(
    work: Path, n_views: int, img: int, frames: int, uv_cache: Path, height: int | None = None, ext: str = ".png"
):
    """``n_views`` cameras of ``img`` x ``height`` (default square) pixels; images stored as ``ext`` (.png/.jpg)."""
    from gsavatar.data_schema.template import Template
    from gsavatar.utils.io import write_image

    import open3d as o3d

    Vb, Fb = icosphere(5)
    Va, Fa = icosphere(4)
    body = Vb * np.array([0.22, 0.75, 0.14]) + np.array([0.0, 1.0, 0.0])
    arm = Va * np.array([0.05, 0.33, 0.05]) + np.array([0.30, 1.05, 0.06])
    V = np.concatenate([body, arm]).astype(np.float32)
    F = np.concatenate([Fb, Fa + len(Vb)])
    t = Template(V, F, np.zeros((len(V), 1), np.int32), np.ones((len(V), 1), np.float32))
    t0 = time.perf_counter()
    t = ensure_uvs(t, uv_cache)
    print(f"xatlas unwrap (or cache hit) of {len(F)} triangles: {time.perf_counter() - t0:.2f} s")
    cams = {}
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = np.array([2.6 * np.sin(a), 1.0 + (0.5 if i % 2 else -0.2), 2.6 * np.cos(a)])
        R, T = look_at(eye, np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0]))
        W, H = img, height or img
        f = 1.25 * min(W, H)
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
        cams[f"cam{i:02d}"] = Camera(f"cam{i:02d}", K, R, T, np.zeros(5), W, H)
    posed = []
    for fr in range(frames):  # rigid motion per frame; the texture stays attached to the rest surface
        ang = 0.2 * fr
        Rz = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
        Vp = (V.astype(np.float64) @ Rz.T + np.array([0.05 * fr, 0, 0])).astype(np.float32)
        posed.append(Vp)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(Vp), o3d.core.Tensor(F.astype(np.uint32)))
        for name, cam in cams.items():
            rays = pixel_rays(cam.K, cam.R, cam.T, cam.width, cam.height)
            hit = scene.cast_rays(o3d.core.Tensor(rays))
            prim = hit["primitive_ids"].numpy().astype(np.int64)
            buv = hit["primitive_uvs"].numpy().astype(np.float64)
            m = np.isfinite(hit["t_hit"].numpy())
            image = np.full((cam.height, cam.width, 3), 0.05, np.float32)
            tri = F[prim[m]]
            w = np.stack([1 - buv[m][:, 0] - buv[m][:, 1], buv[m][:, 0], buv[m][:, 1]], 1)
            rest = (V[tri].astype(np.float64) * w[..., None]).sum(1)
            image[m] = _albedo(rest)
            write_image(work / "images" / name / f"{fr:08d}{ext}", image)
            write_image(work / "masks" / name / f"{fr:08d}.png", m.astype(np.float32))
    cap = Capture(work, 30.0, frames, cams, None, t, None, {}, {n: ext for n in cams})  # type: ignore[arg-type]
    return cap, posed


def builtin_gt(template, tm) -> np.ndarray:
    """Albedo at every texel's rest surface point (0 where no triangle)."""
    gt = np.zeros((tm.size, tm.size, 3), np.float32)
    v = tm.face >= 0
    tri = template.faces[tm.face[v]]
    rest = (template.vertices[tri].astype(np.float64) * tm.bary[v][..., None]).sum(1)
    gt[v] = _albedo(rest)
    return gt


# --------------------------------------------------------------------------- metrics
def psnr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size == 0:
        return float("nan")
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(1 / max(mse, 1e-20))


def capture_gt(root: Path, frame: int, size: int) -> np.ndarray:
    import cv2

    from gsavatar.utils.io import read_image

    gt = read_image(root / "gt" / "textures" / f"{frame:08d}.png")
    if gt.shape[:2] != (size, size):
        interp = cv2.INTER_AREA if gt.shape[0] > size else cv2.INTER_LINEAR
        gt = cv2.resize(gt, (size, size), interpolation=interp)
    return gt


# --------------------------------------------------------------------------- main
def project_parts(proj: UVProjector, vertices: np.ndarray, views: list, reps: int = 7) -> dict[str, float]:
    """Seconds (medians over ``reps`` interleaved repeats) of the parts of one z-buffer projection: the whole
    ``project``, the RGBA region buffers of all views, texel surface + rasterization (the rest of the per-view
    set-up), and the fused sampling + fusion kernel (called as ``project`` calls it)."""
    from numba.typed import List

    from gsavatar.prep import zbuffer as zb
    from gsavatar.prep.project_uv import BLOCK

    cfg = proj.config
    S = proj.size
    zf = proj._zbuffer_views(vertices, views, 0)
    out = (np.zeros((S * S, 3), np.float32), np.zeros(S * S, np.uint8), np.zeros(S * S, np.uint8))
    parts = {
        "project": lambda: proj.project(vertices, views),
        "ctx": lambda: [proj._view_ctx(v, 0, keep_uint8=True, quad=True, slot=i) for i, v in enumerate(views)],
        "setup": lambda: proj._zbuffer_views(vertices, views, 0),
        "kernel": lambda: zb.project_frame(
            zf.P,
            zf.Nrm,
            proj._z_tri,
            proj.faces,
            np.stack(zf.cams),
            List(zf.imgs),
            zf.imgs[0].dtype == np.uint8,
            True,
            List(zf.tri_ids),
            List(zf.planes),
            float(cfg.occlusion_eps),
            float(cfg.min_cos),
            cfg.fusion == "median_band",
            float(cfg.band[0]),
            float(cfg.band[1]),
            BLOCK,
            proj._z_texels,
            *out,
        ),
    }
    ts: dict[str, list[float]] = {k: [] for k in parts}
    for fn in parts.values():
        fn()  # warm-up
    for _ in range(reps):
        for k, fn in parts.items():
            t0 = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t0)
    m = {k: float(np.median(v)) for k, v in ts.items()}
    return {
        "project": m["project"],
        "RGBA region buffers": m["ctx"],
        "surface + rasterization": m["setup"] - m["ctx"],
        "sampling + fusion kernel": m["kernel"],
        "rest": m["project"] - m["setup"] - m["kernel"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--capture", type=Path, help="synthetic capture directory (with gt/textures); default: built-in scene"
    )
    ap.add_argument("--frames", type=int, nargs="+", help="frames to project (default: first 2 train frames / 0 1)")
    ap.add_argument("--cams", nargs="+", help="cameras (default: all)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--views", type=int, default=16, help="built-in scene: number of views")
    ap.add_argument("--img", type=int, default=1024, help="built-in scene: image width (and height unless --height)")
    ap.add_argument("--height", type=int, default=0, help="built-in scene: image height (0 = --img)")
    ap.add_argument("--jpeg", action="store_true", help="built-in scene: JPEG images (masks stay PNG)")
    ap.add_argument(
        "--thuman4", action="store_true", help="built-in scene of THuman4.0's size: 24 views of 1330x1150 JPEG"
    )
    ap.add_argument("--no-mean", action="store_true", help="skip the 'mean' fusion comparison")
    ap.add_argument("--no-parts", action="store_true", help="skip the per-part timing of one frame's projection")
    ap.add_argument(
        "--no-stage-loop",
        action="store_true",
        help="skip timing the stage's read + project loop with and without reading the next frame ahead",
    )
    ap.add_argument(
        "--visibility",
        nargs="+",
        default=["zbuffer"],
        choices=["zbuffer", "rays"],
        help="visibility paths to time (ProjectConfig.visibility)",
    )
    ap.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[1],
        help="numba threads of the z-buffer path (torch.set_num_threads; the rays path ignores it)",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the table (and decode/reader times) as JSON")
    ap.add_argument("--uv-cache", type=Path, default=Path(tempfile.gettempdir()) / "gsavatar_uv_cache")
    args = ap.parse_args()
    if args.thuman4:
        args.views, args.img, args.height, args.jpeg = 24, 1330, 1150, True

    tmp = None
    if args.capture is not None:
        from gsavatar.data_schema.capture import load_capture
        from gsavatar.prep.pose_template import pose_vertices

        cap = load_capture(args.capture)
        if cap.template.corner_uvs is None:
            raise SystemExit("the capture template has no UVs: gt/textures cannot be compared")
        frames = args.frames or cap.splits["train"].frames[:2]
        posed = list(pose_vertices(cap, frames))
        src = f"capture {args.capture}"
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench_project_uv_")
        n = max(args.frames) + 1 if args.frames else 2
        frames = args.frames or [0, 1]
        t0 = time.perf_counter()
        cap, posed_all = builtin_scene(
            Path(tmp.name), args.views, args.img, n, args.uv_cache, args.height or None, ".jpg" if args.jpeg else ".png"
        )
        posed = [posed_all[f] for f in frames]
        src = (
            f"built-in ellipsoid scene ({args.views} views {args.img}x{args.height or args.img} "
            f"{'JPEG' if args.jpeg else 'PNG'}, rendered in {time.perf_counter() - t0:.1f} s)"
        )
    cams = args.cams or list(cap.cameras)
    template = cap.template
    print(f"# bench_project_uv: {src}; {len(template.faces)} triangles, {len(cams)} views, frames {frames}")
    print(f"# {platform.processor() or platform.machine()}, python {platform.python_version()}")

    # I/O floor: decode every frame's images and masks (done once, reused for every size)
    views_of, io_s = {}, []
    for f in frames:
        t0 = time.perf_counter()
        views_of[f] = load_frame_views(cap, f, cams, uint8=True)  # as the project-uv stage reads them
        io_s.append(time.perf_counter() - t0)
    io = float(np.mean(io_s))
    # raw decode only (OpenCV, 8-bit, no float conversion or checks): the floor no reader can go below
    import cv2

    raw_s = []
    for f in frames:
        t0 = time.perf_counter()
        for c in cams:
            assert cv2.imread(str(cap.image_path(c, f)), cv2.IMREAD_COLOR) is not None
            assert cv2.imread(str(cap.mask_path(c, f)), cv2.IMREAD_UNCHANGED) is not None
        raw_s.append(time.perf_counter() - t0)
    raw = float(np.mean(raw_s))
    print(
        f"# decode per frame: {raw:.3f} s raw (cv2.imread of {len(cams)} images + masks), {io:.3f} s through "
        f"gsavatar's readers (8-bit images kept as uint8 as the stage does, mask decoding and checks)"
    )

    def raw_decode(f: int) -> float:
        t0 = time.perf_counter()
        for c in cams:
            assert cv2.imread(str(cap.image_path(c, f)), cv2.IMREAD_COLOR) is not None
            assert cv2.imread(str(cap.mask_path(c, f)), cv2.IMREAD_UNCHANGED) is not None
        return time.perf_counter() - t0

    import torch

    threads0 = torch.get_num_threads()
    rows = []
    for size in args.sizes:
        t0 = time.perf_counter()
        tm = build_texel_map(template, size=size, gutter=ProjectConfig().gutter_px)
        t_map = time.perf_counter() - t0
        gt_of = {
            f: builtin_gt(template, tm) if args.capture is None else capture_gt(args.capture, f, size) for f in frames
        }
        for vis in args.visibility:
            for nth in args.threads if vis == "zbuffer" else [1]:
                torch.set_num_threads(nth)
                cfg = ProjectConfig(tex_size=size, visibility=vis)
                proj = UVProjector(template.faces, tm, cfg, template.face_uv_mask)
                proj_mean = UVProjector(template.faces, tm, replace(cfg, fusion="mean"), template.face_uv_mask)
                proj.project(posed[0], views_of[frames[0]], frame=frames[0])  # warm-up (JIT compile, per-camera setup)
                secs, decs, p_med, p_mean, seen2 = [], [], [], [], []
                for f, V in zip(frames, posed):
                    decs.append(raw_decode(f))
                    t0 = time.perf_counter()
                    fus = proj.project(V, views_of[f], frame=f)
                    secs.append(time.perf_counter() - t0)
                    gt = gt_of[f]
                    m = fus.valid & (fus.seen >= 2)
                    seen2.append(m.sum() / max(proj.num_texels, 1))
                    p_med.append(psnr(fus.texture[m], gt[m]))
                    if not args.no_mean:
                        fm = proj_mean.project(V, views_of[f], frame=f)
                        p_mean.append(psnr(fm.texture[m], gt[m]))
                s, d = float(np.mean(secs)), float(np.mean(decs))
                rows.append(
                    (
                        size,
                        vis,
                        nth if vis == "zbuffer" else 1,
                        t_map,
                        proj.num_texels,
                        s,
                        d,
                        io,
                        proj.num_texels / s,
                        float(np.mean(seen2)),
                        float(np.mean(p_med)),
                        float(np.mean(p_mean)) if p_mean else float("nan"),
                    )
                )
    # the stage's loop (read a frame, project it), with the next frame read in a background thread or not;
    # largest size, z-buffer path, each thread count; 3 alternating repeats, medians
    stage = None
    if "zbuffer" in args.visibility and not args.no_stage_loop:
        size = max(args.sizes)
        tm = build_texel_map(template, size=size, gutter=ProjectConfig().gutter_px)
        proj = UVProjector(template.faces, tm, ProjectConfig(tex_size=size), template.face_uv_mask)
        proj.project(posed[0], views_of[frames[0]], frame=frames[0])
        pose_of = dict(zip(frames, posed))
        loop_s: dict[tuple[int, bool], list[float]] = {}
        for rep in range(3):
            for nth in args.threads:
                torch.set_num_threads(nth)
                for ahead in (False, True):
                    t0 = time.perf_counter()
                    for f, views in prefetched_frame_views(cap, frames, cams, uint8=True, ahead=ahead):
                        proj.project(pose_of[f], views, frame=f)
                    loop_s.setdefault((nth, ahead), []).append((time.perf_counter() - t0) / len(frames))
        stage = []
        print(f"\n# the stage's loop at {size}^2 over frames {frames} (median of 3, alternating):")
        for nth in args.threads:
            seq, pre = float(np.median(loop_s[nth, False])), float(np.median(loop_s[nth, True]))
            stage.append(
                {
                    "tex_size": size,
                    "threads": nth,
                    "read_then_project_s_per_frame": seq,
                    "prefetched_s_per_frame": pre,
                    "speedup": seq / pre,
                }
            )
            print(
                f"#   {nth} thread(s): read then project {seq:.3f} s/frame, "
                f"next frame read meanwhile {pre:.3f} s/frame "
                f"({seq / pre:.2f}x)"
            )
    parts = None
    if "zbuffer" in args.visibility and not args.no_parts:
        size = max(args.sizes)
        torch.set_num_threads(min(args.threads))
        tm = build_texel_map(template, size=size, gutter=ProjectConfig().gutter_px)
        proj = UVProjector(template.faces, tm, ProjectConfig(tex_size=size), template.face_uv_mask)
        parts = project_parts(proj, posed[-1], views_of[frames[-1]])
        print(
            f"\n# where one frame's projection goes at {size}^2, {min(args.threads)} thread(s) (medians of 7): "
            + ", ".join(f"{k} {v:.3f} s" for k, v in parts.items())
        )
    torch.set_num_threads(threads0)

    print()
    print(
        "| tex size | visibility | threads | texel map (s, once) | texels projected | project s/frame "
        "| raw decode s/frame | **project / raw decode** | read s/frame | project / read | texels/s | seen>=2 "
        "| PSNR median_band (dB) | PSNR mean (dB) |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for size, vis, nth, t_map, n, s, d, io_, tps, s2, pm, pmean in rows:
        print(
            f"| {size} | {vis} | {nth} | {t_map:.2f} | {n:,} | {s:.3f} | {d:.3f} | **{s / d:.2f}** | "
            f"{io_:.3f} | {s / io_:.2f} | "
            f"{tps / 1e6:.2f} M | {100 * s2:.0f} % | {pm:.2f} | {pmean:.2f} |"
        )
    if args.json is not None:
        import json

        keys = (
            "tex_size",
            "visibility",
            "threads",
            "texel_map_s",
            "texels",
            "project_s_per_frame",
            "raw_decode_s_per_frame",
            "read_s_per_frame",
            "texels_per_s",
            "seen_ge2_fraction",
            "psnr_median_band_db",
            "psnr_mean_db",
        )
        out = {
            "source": src,
            "machine": f"{platform.processor() or platform.machine()}, python {platform.python_version()}",
            "frames": list(map(int, frames)),
            "views": len(cams),
            "rows": [{**dict(zip(keys, r)), "project_over_raw_decode": r[5] / r[6]} for r in rows],
            "stage_loop": stage,
            "parts_s": parts,
        }
        args.json.write_text(json.dumps(out, indent=1, default=float, allow_nan=True))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
