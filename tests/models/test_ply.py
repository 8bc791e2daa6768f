from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.models import AvatarOutput, export_frame_ply, ply_property_names, read_ply, write_ply

STANDARD_DEG1 = (
    "x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 "
    + " ".join(f"f_rest_{i}" for i in range(9))
    + " opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3"
).split()


def _gaussians(N=57, K=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(N, 4, generator=g)
    return dict(
        means=torch.randn(N, 3, generator=g),
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(N, 3, generator=g) * 0.05 + 1e-4,
        opacities=torch.rand(N, generator=g) * 0.98 + 0.01,
        sh=torch.randn(N, K, 3, generator=g),
    )


@pytest.mark.parametrize("K", [1, 4, 9])
def test_round_trip(tmp_path, K):
    g = _gaussians(K=K)
    path = tmp_path / "out" / "frame.ply"
    write_ply(path, **g)
    r = read_ply(path)
    assert r.property_names == ply_property_names(K)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_allclose(getattr(r, name), g[name].numpy(), rtol=1e-5, atol=1e-6, err_msg=name)
    assert not list(path.parent.glob(".*"))  # atomic write leaves no temp file


def test_header_is_the_standard_layout(tmp_path):
    g = _gaussians(N=3, K=4)
    path = tmp_path / "a.ply"
    write_ply(path, **g)
    raw = path.read_bytes()
    head = raw[: raw.index(b"end_header\n")].decode().splitlines()
    # a comment line marks the file as gsavatar's (single-file output rule, docs/reliability.md); readers skip it
    assert head[:4] == ["ply", "format binary_little_endian 1.0", "comment gsavatar-output 3dgs", "element vertex 3"]
    assert [ln.split()[2] for ln in head[4:]] == STANDARD_DEG1
    assert all(ln.split()[1] == "float" for ln in head[4:])
    assert len(raw) == raw.index(b"end_header\n") + len(b"end_header\n") + 3 * len(STANDARD_DEG1) * 4
    # stored (raw) values: logit opacity, log scale, channel-major f_rest
    data = np.frombuffer(raw[raw.index(b"end_header\n") + 11 :], "<f4").reshape(3, -1)
    col = {n: i for i, n in enumerate(STANDARD_DEG1)}
    o = g["opacities"].numpy()
    np.testing.assert_allclose(data[:, col["opacity"]], np.log(o / (1 - o)), rtol=1e-5)
    np.testing.assert_allclose(data[:, col["scale_1"]], np.log(g["scales"][:, 1].numpy()), rtol=1e-5)
    # f_rest_{c*(K-1)+k} = sh[:, k+1, c]: channel 1 (green), coefficient 2 -> f_rest_4
    np.testing.assert_allclose(data[:, col["f_rest_4"]], g["sh"][:, 2, 1].numpy(), rtol=1e-6)
    np.testing.assert_allclose(data[:, col["f_dc_2"]], g["sh"][:, 0, 2].numpy(), rtol=1e-6)


def test_export_frame_and_errors(tmp_path):
    g = _gaussians(N=5, K=4)
    other = _gaussians(N=5, K=4, seed=1)
    B = lambda k: torch.stack([other[k], g[k]])  # noqa: E731  frame 1 holds g
    out = AvatarOutput(B("means"), B("quats"), B("scales"), B("opacities"), B("sh"), torch.zeros(2, 2, 3), B("means"))
    export_frame_ply(tmp_path / "f.ply", out, frame=1)
    r = read_ply(tmp_path / "f.ply")
    np.testing.assert_allclose(r.means, g["means"].numpy(), rtol=1e-6)
    np.testing.assert_allclose(r.sh, g["sh"].numpy(), rtol=1e-6)
    with pytest.raises(ValueError, match=r"quats must be \[5, 4\]"):
        write_ply(tmp_path / "x.ply", g["means"], g["quats"][:, :3], g["scales"], g["opacities"], g["sh"])
    with pytest.raises(ValueError, match="sh must be"):
        write_ply(tmp_path / "x.ply", g["means"], g["quats"], g["scales"], g["opacities"], g["sh"][:, :3])
    assert not (tmp_path / "x.ply").exists()
