"""Time forward + backward of the CPU renderer (``gsavatar.render.rasterize``).

Not a test. The scene is avatar-like: N Gaussians on the surface of a 1.7 m
tall union of ellipsoids (torso, head, limbs), surface-aligned flat scales sized
to the point spacing (so denser models get smaller splats, as trained ones do),
opacities in [0.3, 1], seen by C cameras on a ring at 2.6 m.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_rasterizer.py
    PYTHONPATH=src .venv/bin/python benchmarks/bench_rasterizer.py --gaussians 20000 \
        --resolutions 256 --cameras 4
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time

import torch

from gsavatar.render import rasterize

# (centre xyz, semi-axes xyz) in metres; y is up in this toy world.
_BODY_PARTS = [
    ((0.0, 1.25, 0.0), (0.17, 0.28, 0.11)),  # torso
    ((0.0, 1.62, 0.0), (0.09, 0.11, 0.10)),  # head
    ((-0.10, 0.50, 0.0), (0.07, 0.45, 0.07)),  # legs
    ((0.10, 0.50, 0.0), (0.07, 0.45, 0.07)),
    ((-0.30, 1.20, 0.0), (0.05, 0.30, 0.05)),  # arms
    ((0.30, 1.20, 0.0), (0.05, 0.30, 0.05)),
]


def avatar_scene(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random Gaussians on an ellipsoid-union 'body'.

    Returns:
        dict with means [N, 3], quats [N, 4] wxyz, scales [N, 3], opacities [N],
        colors [N, 3] (all float32, world frame, metres)
    """
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor([p[0] for p in _BODY_PARTS])
    axes = torch.tensor([p[1] for p in _BODY_PARTS])
    # Rough ellipsoid surface areas so points are spread uniformly over the body.
    a, b, c = axes.unbind(-1)
    area = 4 * math.pi * (((a * b) ** 1.6 + (a * c) ** 1.6 + (b * c) ** 1.6) / 3) ** (1 / 1.6)
    part = torch.multinomial(area / area.sum(), n, replacement=True, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    means = centres[part] + dirs * axes[part]
    spacing = math.sqrt(float(area.sum()) / n)
    scales = spacing * 0.6 * torch.exp(0.3 * torch.randn(n, 3, generator=g))
    scales[:, 2] *= 0.15  # flat splats
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": scales,
        "opacities": 0.3 + 0.7 * torch.rand(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
    }


def ring_cameras(n_cams: int, res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cameras looking at the body centre from a 2.6 m ring.

    Returns:
        viewmats: [C, 4, 4] cam_from_world (OpenCV axes), Ks: [C, 3, 3]
    """
    target = torch.tensor([0.0, 1.0, 0.0])
    vms = []
    for i in range(n_cams):
        ang = 2 * math.pi * i / n_cams
        eye = torch.tensor([2.6 * math.sin(ang), 1.1, 2.6 * math.cos(ang)])
        fwd = torch.nn.functional.normalize(target - eye, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0])), dim=0)
        down = torch.linalg.cross(fwd, right)
        rot_cw = torch.stack([right, down, fwd])  # rows: camera axes in world frame
        vm = torch.eye(4)
        vm[:3, :3] = rot_cw
        vm[:3, 3] = -rot_cw @ eye
        vms.append(vm)
    f = 1.1 * res  # ~49 deg horizontal FOV: the body fills ~75 % of the height
    K = torch.tensor([[f, 0.0, res / 2], [0.0, f, res / 2], [0.0, 0.0, 1.0]])
    return torch.stack(vms), K.expand(n_cams, 3, 3).clone()


def time_step(n: int, res: int, n_cams: int, repeats: int) -> dict:
    """Wall times (ms) of a no-grad forward and of forward + backward of one render."""
    scene = avatar_scene(n)
    params = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
    viewmats, Ks = ring_cameras(n_cams, res)
    bg = torch.ones(n_cams, 3)

    def render():
        return rasterize(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            params["colors"],
            viewmats,
            Ks,
            res,
            res,
            bg,
            backend="torch",
        )

    out = render()  # warm-up (allocator, lazy init)
    out.colors.sum().backward()
    fwd, full, cpu = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        with torch.no_grad():
            render()
        fwd.append(time.perf_counter() - t0)
        t0, c0 = time.perf_counter(), time.process_time()
        out = render()
        (out.colors.square().mean() + out.alphas.mean()).backward()
        full.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    med = lambda xs: 1e3 * sorted(xs)[len(xs) // 2]  # noqa: E731
    return {
        "fwd_min": 1e3 * min(fwd),
        "full_min": 1e3 * min(full),
        "full_med": med(full),
        "cpu_med": med(cpu),
        "stats": out.meta["stats"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, nargs="+", default=[1000, 10000, 50000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--cameras", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(
        f"machine: {platform.platform()}, {platform.machine()}, {os.cpu_count()} cpus, "
        f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, "
        f"cameras per render {args.cameras}, load average before run {load}"
    )
    print()
    print(
        "| Gaussians | resolution | fwd ms (min) | fwd+bwd ms (min) | fwd+bwd ms (median) "
        "| fwd+bwd CPU ms (median) | candidates | contributing |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.gaussians:
        for res in args.resolutions:
            r = time_step(n, res, args.cameras, args.repeats)
            st = r["stats"]
            print(
                f"| {n} | {res}x{res} | {r['fwd_min']:.0f} | {r['full_min']:.0f} | {r['full_med']:.0f} "
                f"| {r['cpu_med']:.0f} | {st.n_candidates:,} | {st.n_contributing:,} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
