"""3DGS PLY export checked by independent readers: ``plyfile`` (every property round trips), the up-axis
rotation (rotated and unrotated Gaussians render the same from matching cameras), and, opt-in
(``-m interop``, needs node + ``@playcanvas/splat-transform``), PlayCanvas' splat-transform reading the
file as Gaussian data with the right count and SH bands."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
import torch

from gsavatar.models.ply import (
    UP_AXES,
    WORLD_UP,
    ply_property_names,
    read_ply,
    rotate_gaussians,
    sh_rotation,
    write_ply,
)
from gsavatar.render.rasterize import rasterize

plyfile = pytest.importorskip("plyfile", reason="plyfile is a test dependency: pip install -e '.[test]'")


def _gaussians(N=200, K=4, seed=0, spread=0.4):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(N, 4, generator=g)
    return dict(
        means=torch.randn(N, 3, generator=g) * spread,
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(N, 3, generator=g) * 0.04 + 0.005,
        opacities=torch.rand(N, generator=g) * 0.9 + 0.05,
        sh=torch.randn(N, K, 3, generator=g) * 0.4,
    )


@pytest.mark.parametrize("K", [1, 4, 16])
def test_plyfile_reads_every_property(tmp_path, K):
    g = _gaussians(N=31, K=K)
    path = tmp_path / "g.ply"
    write_ply(path, **g)
    el = plyfile.PlyData.read(str(path))["vertex"]
    names = [p.name for p in el.properties]
    assert names == ply_property_names(K)
    assert all(p.val_dtype in ("f4", "<f4", "float32") for p in el.properties), [p.val_dtype for p in el.properties]
    assert el.count == 31
    d = el.data
    col = lambda *ks: np.stack([d[k] for k in ks], 1)  # noqa: E731
    np.testing.assert_allclose(col("x", "y", "z"), g["means"].numpy(), rtol=1e-6)
    np.testing.assert_array_equal(col("nx", "ny", "nz"), 0)
    np.testing.assert_allclose(col("f_dc_0", "f_dc_1", "f_dc_2"), g["sh"][:, 0].numpy(), rtol=1e-6)
    if K > 1:
        rest = col(*[f"f_rest_{i}" for i in range(3 * (K - 1))]).reshape(31, 3, K - 1).transpose(0, 2, 1)
        np.testing.assert_allclose(rest, g["sh"][:, 1:].numpy(), rtol=1e-6)  # channel-major (INRIA)
    o = g["opacities"].numpy()
    np.testing.assert_allclose(d["opacity"], np.log(o / (1 - o)), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.exp(col("scale_0", "scale_1", "scale_2")), g["scales"].numpy(), rtol=1e-5)
    np.testing.assert_allclose(col("rot_0", "rot_1", "rot_2", "rot_3"), g["quats"].numpy(), rtol=1e-5, atol=1e-6)
    # and back: plyfile writes the same data, our reader reads it (both directions independent of our writer)
    plyfile.PlyData([plyfile.PlyElement.describe(d, "vertex")], byte_order="<").write(str(tmp_path / "again.ply"))
    r = read_ply(tmp_path / "again.ply")
    np.testing.assert_allclose(r.sh, g["sh"].numpy(), rtol=1e-6)
    np.testing.assert_allclose(r.opacities, o, rtol=1e-5)


def test_up_axis_is_a_rotation_of_the_world():
    for axis, R in UP_AXES.items():
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        target = {"z": [0, 0, 1], "-y": [0, -1, 0], "y": [0, 1, 0]}[axis]
        np.testing.assert_allclose(R @ WORLD_UP, target, atol=1e-12)
    # SH rotation: block diagonal, orthogonal, the identity for R = I
    D = sh_rotation(UP_AXES["-y"], 16)
    np.testing.assert_allclose(D @ D.T, np.eye(16), atol=1e-9)
    np.testing.assert_allclose(sh_rotation(np.eye(3), 9), np.eye(9), atol=1e-9)
    for lo, hi in ((0, 1), (1, 4), (4, 9), (9, 16)):
        assert np.abs(D[lo:hi, :lo]).max(initial=0) < 1e-9 and np.abs(D[lo:hi, hi:]).max(initial=0) < 1e-9


def _look_at(eye, target, up):
    """cam_from_world (OpenCV: x right, y down, z forward)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    d = np.cross(f, r)
    M = np.eye(4)
    M[:3, :3] = np.stack([r, d, f])
    M[:3, 3] = -M[:3, :3] @ eye
    return M


@pytest.mark.parametrize("axis", ["-y", "z"])
def test_up_axis_renders_the_same_from_matching_cameras(tmp_path, axis):
    """The file written with --up-axis, read back and rendered from the rotated camera, equals our
    Gaussians rendered from the original camera (positions, rotations and view-dependent SH all rotate)."""
    g = _gaussians(N=300, K=16, spread=0.3)
    write_ply(tmp_path / "ours.ply", **g)
    write_ply(tmp_path / "r.ply", **g, up_axis=axis)
    ours, rot = read_ply(tmp_path / "ours.ply"), read_ply(tmp_path / "r.ply")
    assert not np.allclose(ours.means, rot.means, atol=1e-3)
    R = UP_AXES[axis]
    np.testing.assert_allclose(rot.means, ours.means @ R.T, atol=1e-6)
    W, H = 96, 80
    K = torch.tensor([[90.0, 0, W / 2], [0, 90.0, H / 2], [0, 0, 1]])[None]
    images = []
    for gs, vm in ((ours, _look_at(np.array([1.2, -1.6, 0.5]), np.zeros(3), np.array([0.0, 0, 1]))), (rot, None)):
        if vm is None:  # the same camera in the rotated world: cam_from_world' = cam_from_world @ R^-1
            vm = images[0][1] @ np.linalg.inv(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
        out = rasterize(
            torch.from_numpy(gs.means),
            torch.from_numpy(gs.quats),
            torch.from_numpy(gs.scales),
            torch.from_numpy(gs.opacities),
            torch.from_numpy(gs.sh),
            torch.from_numpy(vm).float()[None],
            K,
            W,
            H,
            torch.zeros(1, 3),
            sh_degree=3,
            backend="torch",
        )
        images.append((out.colors[0], vm))
    a, b = images[0][0], images[1][0]
    assert a.abs().max() > 0.1  # something is drawn
    assert (a - b).abs().max() < 2e-3, float((a - b).abs().max())
    # SH alone: without rotating the coefficients the view-dependent colour would differ
    m, q, c = rotate_gaussians(R, ours.means, ours.quats, ours.sh)
    assert np.abs(c[:, 1:] - ours.sh[:, 1:]).max() > 0.1


def _splat_transform() -> list[str] | None:
    exe = shutil.which("splat-transform")
    if exe:
        return [exe]
    if shutil.which("npx") and shutil.which("node"):
        r = subprocess.run(["npx", "--no-install", "splat-transform", "--version"], capture_output=True, timeout=60)
        if r.returncode == 0:
            return ["npx", "--no-install", "splat-transform"]
    return None


@pytest.mark.interop
@pytest.mark.parametrize("K", [1, 4, 16])
def test_splat_transform_reads_our_ply(tmp_path, K):
    cmd = _splat_transform()
    if cmd is None:
        pytest.skip("interop: needs node and `npm install -g @playcanvas/splat-transform`")
    g = _gaussians(N=123, K=K)
    write_ply(tmp_path / "a.ply", **g, up_axis="-y")
    r = subprocess.run(
        [*cmd, str(tmp_path / "a.ply"), "--summary", "null"], capture_output=True, text=True, timeout=120
    )
    text = r.stdout + r.stderr
    assert r.returncode == 0, text
    m = re.search(r"(\d+) gaussians\W+(\d+) SH bands", text)
    assert m, text
    assert (int(m.group(1)), int(m.group(2))) == (123, round(np.sqrt(K)) - 1), text
    # its CSV export: the values it decoded are ours
    r = subprocess.run(
        [*cmd, str(tmp_path / "a.ply"), str(tmp_path / "a.csv")], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stdout + r.stderr
    lines = (tmp_path / "a.csv").read_text().splitlines()
    head = lines[0].split(",")
    vals = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert head == ply_property_names(K) and vals.shape == (123, len(head))
    ours = read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(vals[:, :3], ours.means, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.exp(vals[:, head.index("scale_0")]), ours.scales[:, 0], rtol=1e-5)


@pytest.mark.parametrize("axis", ["y", "-y", "z"])
def test_written_body_stands_along_the_files_up_axis(tmp_path, tiny_capture, axis):
    """Against the capture itself: its cameras' image-down is -WORLD_UP and its body's head lies above its feet
    along WORLD_UP; in a file written with ``up_axis`` the head lies above the feet along that axis."""
    from gsavatar.data_schema import load_capture

    cap = load_capture(tiny_capture)
    down = np.mean([np.asarray(c.cam_from_world)[1, :3] for c in cap.cameras.values()], 0)
    assert down @ WORLD_UP < -0.9  # every dome camera is upright
    v = np.asarray(cap.template.vertices, np.float64)
    N = len(v)
    write_ply(
        tmp_path / "body.ply",
        v,
        np.tile([1.0, 0, 0, 0], (N, 1)),
        np.full((N, 3), 0.01),
        np.full(N, 0.5),
        np.zeros((N, 1, 3)),
        up_axis=axis,
    )
    means = read_ply(tmp_path / "body.ply").means
    up = {"y": [0, 1, 0], "-y": [0, -1, 0], "z": [0, 0, 1]}[axis]
    height = means @ np.asarray(up, np.float64)
    head_joint = [j.name for j in cap.rig.joints].index("Head")
    head = cap.rig.heads()[head_joint] @ WORLD_UP
    assert head > 1.0 and height.max() - height.min() > 1.0  # metres: a standing adult
    np.testing.assert_allclose(height, v @ WORLD_UP, atol=1e-5)  # the file's up is our up
