from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.data_schema.pose_pca import PosePCA
from gsavatar.data_schema.rig import BODY_GROUPS
from gsavatar.prep.pca import fit_pose_pca
from gsavatar.utils.errors import SchemaError
from prep_fixtures import body_rig


def _poses(rig, F=200, seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    P = rig.pose_dim
    # correlated within the whole vector (so a global PCA would mix groups)
    A = rng.normal(size=(P, P)) / np.sqrt(P)
    return (rng.normal(size=(F, P)) @ A) * scale + rng.normal(size=P) * 0.1


def _naive_project(poses_train, rig, x, n=5, clamp=2.0, mode="local"):
    """Reference: explicit per-group loops with numpy SVD."""
    sg = rig.slot_groups()
    groups = (
        [np.flatnonzero(sg == g) for g in range(len(BODY_GROUPS))] if mode == "local" else [np.arange(rig.pose_dim)]
    )
    out = np.zeros_like(x)
    F = len(poses_train)
    for slots in groups:
        Xg = poses_train[:, slots]
        mu = Xg.mean(0)
        U, s, Vt = np.linalg.svd(Xg - mu, full_matrices=False)
        k = min(n, len(slots), F - 1)
        k = min(k, int(np.sum(s > 1e-9)))
        for b in range(len(x)):
            y = mu.copy()
            for c in range(k):
                sigma = s[c] / np.sqrt(F - 1)
                coef = float(np.dot(x[b, slots] - mu, Vt[c]))
                coef = min(max(coef, -clamp * sigma), clamp * sigma)
                y += coef * Vt[c]
            out[b, slots] = y
    return out


@pytest.mark.parametrize("mode", ["local", "global"])
def test_matches_naive_reference(mode):
    rig = body_rig()
    tr = _poses(rig)
    n = 5 if mode == "local" else 12
    pca = fit_pose_pca(tr, rig, n_components=n, mode=mode)
    x = _poses(rig, F=17, seed=1, scale=0.6)  # partly outside ±2σ -> clamping active
    got = pca.project(x)
    ref = _naive_project(tr, rig, x, n=n, mode=mode)
    np.testing.assert_allclose(got, ref, atol=1e-10)
    if mode == "local":
        assert pca.components_per_group() == {
            g: min(5, int(np.sum(rig.slot_groups() == i))) for i, g in enumerate(BODY_GROUPS)
        }
    else:
        assert pca.num_components == 12


def test_exact_reconstruction_full_rank_within_range():
    rig = body_rig()
    tr = _poses(rig, F=300)
    pca = fit_pose_pca(tr, rig, n_components=100, mode="local", clamp_sigma=1e6)
    assert pca.num_components == rig.pose_dim
    np.testing.assert_allclose(pca.project(tr[:50]), tr[:50], atol=1e-10)
    # with the default ±2σ: a pose whose coefficients are all within 2σ is reproduced exactly
    pca2 = fit_pose_pca(tr, rig, n_components=100, mode="local")
    z = pca2.transform(tr)
    inside = np.all(np.abs(z) <= 2 * pca2.sigma, axis=1)
    assert inside.sum() > 0
    np.testing.assert_allclose(pca2.project(tr[inside]), tr[inside], atol=1e-10)
    assert not np.allclose(pca2.project(tr[~inside]), tr[~inside])


def test_clamping():
    rig = body_rig()
    tr = _poses(rig)
    pca = fit_pose_pca(tr, rig, n_components=5)
    # push one coefficient to 10σ: after projection it sits exactly at +2σ, others unchanged
    z = pca.transform(tr[:1]).copy()
    z = np.clip(z, -pca.sigma, pca.sigma)  # start well inside
    c = 3
    z[0, c] = 10 * pca.sigma[c]
    x = pca.inverse(z)
    z2 = pca.transform(pca.project(x))
    np.testing.assert_allclose(z2[0, c], 2 * pca.sigma[c], rtol=1e-10)
    others = np.arange(pca.num_components) != c
    np.testing.assert_allclose(z2[0, others], z[0, others], atol=1e-10)
    # all projected coefficients obey the bound
    far = _poses(rig, F=50, seed=5, scale=5.0)
    zf = pca.transform(pca.project(far))
    assert np.all(np.abs(zf) <= 2 * pca.sigma * (1 + 1e-9))


def test_local_never_mixes_groups():
    rig = body_rig()
    tr = _poses(rig)
    pca = fit_pose_pca(tr, rig, n_components=5, mode="local")
    sg = rig.slot_groups()
    x = _poses(rig, F=4, seed=2, scale=0.8)
    base = pca.project(x)
    for g in range(len(BODY_GROUPS)):
        slot = int(np.flatnonzero(sg == g)[0])
        xp = x.copy()
        xp[:, slot] += 3.0
        out = pca.project(xp)
        other = sg != g
        assert np.array_equal(out[:, other], base[:, other])
        # torch too
        ot = pca.project(torch.as_tensor(xp)).numpy()
        bt = pca.project(torch.as_tensor(x)).numpy()
        assert np.array_equal(ot[:, other], bt[:, other])
    # every basis column lives in exactly one group
    for c in range(pca.num_components):
        nz = np.flatnonzero(pca.basis[:, c])
        assert np.all(sg[nz] == pca.component_group[c])
    # global PCA does mix (sanity of the test data)
    glob = fit_pose_pca(tr, rig, n_components=10, mode="global")
    xp = x.copy()
    xp[:, 0] += 3.0
    assert not np.allclose(glob.project(xp)[:, sg != sg[0]], glob.project(x)[:, sg != sg[0]])


def test_rank_deficient_groups():
    rig = body_rig()
    sg = rig.slot_groups()
    tr = _poses(rig, F=200)
    lh = np.flatnonzero(sg == BODY_GROUPS.index("left_hand"))
    rh = np.flatnonzero(sg == BODY_GROUPS.index("right_hand"))
    ll = np.flatnonzero(sg == BODY_GROUPS.index("left_leg"))
    tr[:, lh] = 0.25  # constant group: zero variance everywhere
    tr[:, rh[1:]] = tr[:, rh[:1]] * np.arange(2, len(rh) + 1)  # rank-1 group
    tr[:, ll[0]] = -1.0  # one zero-variance param in a group
    pca = fit_pose_pca(tr, rig, n_components=5)
    cpg = pca.components_per_group()
    assert cpg["left_hand"] == 0 and cpg["right_hand"] == 1 and cpg["left_leg"] == 2
    assert np.all(np.isfinite(pca.basis)) and np.all(pca.sigma > 0)
    x = _poses(rig, F=6, seed=3, scale=0.8)
    y = pca.project(x)
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y[:, lh], 0.25)
    np.testing.assert_allclose(y[:, ll[0]], -1.0)
    np.testing.assert_allclose(y, _naive_project(tr, rig, x), atol=1e-9)


def test_fewer_frames_than_dims():
    rig = body_rig()
    tr = _poses(rig, F=3)  # F-1 = 2 components at most
    pca = fit_pose_pca(tr, rig, n_components=5)
    assert all(
        v == min(2, int(np.sum(rig.slot_groups() == i))) for i, v in enumerate(pca.components_per_group().values())
    )
    np.testing.assert_allclose(pca.project(tr), _naive_project(tr, rig, tr), atol=1e-10)
    one = fit_pose_pca(tr[:1], rig)
    assert one.num_components == 0
    np.testing.assert_allclose(one.project(tr), np.repeat(tr[:1], 3, 0))
    glob = fit_pose_pca(tr, rig, n_components=50, mode="global")
    assert glob.num_components == 2


def test_torch_same_numbers_and_differentiable():
    rig = body_rig()
    tr = _poses(rig)
    pca = fit_pose_pca(tr, rig)
    x = _poses(rig, F=8, seed=4, scale=0.6)
    ref = pca.project(x)
    t64 = pca.project(torch.as_tensor(x))
    assert t64.dtype == torch.float64
    np.testing.assert_allclose(t64.numpy(), ref, atol=1e-12)
    t32 = torch.as_tensor(x, dtype=torch.float32).requires_grad_(True)
    y = pca.project(t32)
    assert y.dtype == torch.float32
    np.testing.assert_allclose(y.detach().numpy(), ref, atol=1e-5)
    np32 = pca.project(x.astype(np.float32))
    assert np32.dtype == np.float32
    np.testing.assert_allclose(np32, ref, atol=1e-5)
    y.sum().backward()
    assert t32.grad is not None and torch.all(torch.isfinite(t32.grad))
    # gradient = B_active B_active^T 1 (only unclamped components pass gradient)
    z = pca.transform(x.astype(np.float32))
    active = np.abs(z) < 2 * pca.sigma
    for b in range(2):
        Ba = pca.basis[:, active[b]]
        np.testing.assert_allclose(t32.grad[b].numpy(), Ba @ (Ba.T @ np.ones(rig.pose_dim)), atol=1e-4)


def test_save_load_roundtrip(tmp_path):
    rig = body_rig()
    tr = _poses(rig)
    for mode in ("local", "global"):
        pca = fit_pose_pca(tr, rig, mode=mode, n_components=5 if mode == "local" else 9, clamp_sigma=1.5)
        p = tmp_path / f"pca_{mode}.npz"
        pca.save(p)
        back = PosePCA.load(p)
        assert back.mode == mode and back.clamp_sigma == 1.5 and back.param_names == pca.param_names
        assert back.header() == pca.header()
        x = _poses(rig, F=5, seed=9)
        np.testing.assert_array_equal(back.project(x), pca.project(x))
        back.check_rig(rig)
    np.savez(tmp_path / "bad.npz", header=np.array('{"format": "other"}'))
    with pytest.raises(SchemaError, match="format"):
        PosePCA.load(tmp_path / "bad.npz")
    with pytest.raises(SchemaError, match="not found"):
        PosePCA.load(tmp_path / "missing.npz")


def test_input_validation():
    rig = body_rig()
    with pytest.raises(ValueError, match="poses must be"):
        fit_pose_pca(np.zeros((5, 3)), rig)
    bad = _poses(rig)
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_pose_pca(bad, rig)
    pca = fit_pose_pca(_poses(rig), rig)
    with pytest.raises(ValueError, match="poses must be"):
        pca.project(np.zeros((2, 3)))
