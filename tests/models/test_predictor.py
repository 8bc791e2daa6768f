"""Appearance predictor: shapes, causality, latent PCA clamp, streaming == rollout, root-motion invariance."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from gsavatar.geometry.lbs import KinematicChain
from gsavatar.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from gsavatar.models.predictor import (
    AppearancePredictor,
    PredictorConfig,
    fit_latent_pca,
    heading_frame,
    latent_pca_project,
    memory_features,
    relative_root_motion,
    window_features,
)

A, L, P, N = 5, 6, 8, 4
SMALL = PredictorConfig(
    history=N, width=32, heads=2, ff=64, latent_dim=L, token_hidden=16, latent_pca_components=4, initial_hidden=16
)


def model(untrained: bool = False, **kw) -> AppearancePredictor:
    torch.manual_seed(0)
    m = AppearancePredictor(SMALL.__class__(**{**SMALL.to_json(), **kw}), A, [0, 2, 3, 5, 7], P, seed=0)
    if not untrained:
        with torch.no_grad():  # a visibly input-dependent output (the residual head starts at zero)
            m.head.weight.copy_(torch.randn(m.head.weight.shape, generator=torch.Generator().manual_seed(3)) * 0.3)
    return m.eval()


def seq(T: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float32)[:, None]
    pose = torch.sin(0.3 * t + torch.rand(1, P, generator=g) * 6) + 0.05 * torch.randn(T, P, generator=g)
    rot = 0.2 * torch.randn(T, 3, generator=g) + torch.tensor([0.0, 0.1, 0.0]) * t
    trans = torch.randn(T, 3, generator=g) * 0.1 + torch.tensor([0.03, 0.0, 0.01]) * t
    return pose, rot, trans


def windows(x: torch.Tensor, t: int) -> torch.Tensor:
    """Window ending at t (first frame repeated before 0). [T, D] -> [1, N, D]"""
    idx = torch.clamp(torch.arange(t - N + 1, t + 1), min=0)
    return x[idx][None]


def test_shapes_and_argument_errors():
    m = model()
    pose, rot, trans = seq(7)
    out = m(
        windows(pose, 6).expand(3, -1, -1),
        windows(rot, 6).expand(3, -1, -1),
        windows(trans, 6).expand(3, -1, -1),
        torch.randn(3, A, L),
    )
    assert out.shape == (3, A, L)
    assert m.rollout(pose, rot, trans).shape == (7, A, L)
    lat, st = m.step(m.init_state(pose[0], rot[0], trans[0]), pose[1], rot[1], trans[1])
    assert lat.shape == (A, L) and st.pose.shape == (N, P) and st.latents.shape == (A, L)
    with pytest.raises(ValueError, match=r"pose_window must be \[\*, 4, 8\], got \[1, 3, 8\]"):
        m(pose[None, :3], rot[None, :3], trans[None, :3], torch.zeros(1, A, L))
    with pytest.raises(ValueError, match="prev_latents"):
        m(windows(pose, 3), windows(rot, 3), windows(trans, 3), torch.zeros(1, A + 1, L))
    with pytest.raises(ValueError, match="init_latents"):
        m.init_state(pose[0], rot[0], trans[0], torch.zeros(A, L + 1))


def test_window_features_are_value_velocity_acceleration():
    x = torch.tensor([[0.0, 1.0, 4.0, 9.0]])[..., None]  # [1, 4, 1]
    f = window_features(x)[0, 0]
    assert f.tolist() == [0, 1, 4, 9, 1, 3, 5, 2, 2]


def test_causality_future_and_out_of_window_poses_do_not_matter():
    m = model()
    pose, rot, trans = seq(12)
    t = 7
    prev = torch.randn(1, A, L)
    ref = m(windows(pose, t), windows(rot, t), windows(trans, t), prev)
    for frame, same in ((t + 1, True), (t + 3, True), (t - N, True), (t - N + 1, False), (t, False)):
        p2, r2, s2 = pose.clone(), rot.clone(), trans.clone()
        p2[frame] += 0.7
        r2[frame] += 0.3
        s2[frame] += 0.2
        out = m(windows(p2, t), windows(r2, t), windows(s2, t), prev)
        assert torch.equal(out, ref) == same, frame
    assert not torch.allclose(m(windows(pose, t), windows(rot, t), windows(trans, t), prev + 0.5), ref)
    # free-running rollout: frames after t never change outputs up to t
    full = m.rollout(pose, rot, trans, torch.zeros(A, L))
    p2 = pose.clone()
    p2[t + 1 :] += 1.0
    part = m.rollout(p2, rot, trans, torch.zeros(A, L))
    assert torch.equal(full[: t + 1], part[: t + 1]) and not torch.allclose(full[t + 1 :], part[t + 1 :])


def test_streaming_step_equals_rollout():
    m = model()
    pose, rot, trans = seq(9)
    init = torch.randn(A, L)
    st = m.init_state(pose[0], rot[0], trans[0], init)
    outs = []
    for t in range(9):
        lat, st = m.step(st, pose[t], rot[t], trans[t])
        outs.append(lat)
    assert torch.equal(torch.stack(outs), m.rollout(pose, rot, trans, init))
    # the window-batched path (training / one forward per frame) gives the same numbers
    prev, ref = init[None], []
    for t in range(9):
        prev = m(windows(pose, t), windows(rot, t), windows(trans, t), prev)
        ref.append(prev[0])
    # rtol: the residual output (l_{t-1} + delta) carries float32 round-off of the previous frames along
    torch.testing.assert_close(torch.stack(ref), torch.stack(outs), atol=1e-5, rtol=1e-5)
    tf = m.rollout(pose, rot, trans, init, first_is_given=True)
    assert torch.equal(tf[0], init) and tf.shape == (9, A, L)


def test_reinit_every_replaces_previous_latents():
    m = model()
    pose, rot, trans = seq(6)
    Z = torch.randn(A, L)
    out = m.rollout(pose, rot, trans, torch.zeros(A, L), reinit_every=2, reinit_latents=lambda t: Z)
    ref = m(windows(pose, 4), windows(rot, 4), windows(trans, 4), Z[None])[0]
    torch.testing.assert_close(out[4], ref, atol=1e-6, rtol=0)
    out2 = m(windows(pose, 2), windows(rot, 2), windows(trans, 2), Z[None])
    ref3 = m(windows(pose, 3), windows(rot, 3), windows(trans, 3), out2)[0]
    torch.testing.assert_close(out[3], ref3, atol=1e-6, rtol=0)


def random_rotation(g: torch.Generator) -> torch.Tensor:
    return axis_angle_to_matrix(torch.randn(3, generator=g, dtype=torch.float64) * 1.5)


def test_rigid_transform_of_root_motion_leaves_prediction_unchanged():
    m = model()
    pose, rot, trans = seq(N)
    g = torch.Generator().manual_seed(3)
    Q, c = random_rotation(g), torch.randn(3, generator=g, dtype=torch.float64) * 2
    rot2 = matrix_to_axis_angle(Q @ axis_angle_to_matrix(rot.double())).float()
    trans2 = (trans.double() @ Q.T + c).float()
    torch.testing.assert_close(
        relative_root_motion(rot2[None], trans2[None]), relative_root_motion(rot[None], trans[None]), atol=2e-6, rtol=0
    )
    prev = torch.randn(1, A, L)
    a = m(pose[None], rot[None], trans[None], prev)
    b = m(pose[None], rot2[None], trans2[None], prev)
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    # but root motion inside the window does matter
    trans3 = trans.clone()
    trans3[0] += 0.5
    assert not torch.allclose(m(pose[None], rot[None], trans3[None], prev), a, atol=1e-4)


def test_latent_pca_clamp_box():
    g = torch.Generator().manual_seed(0)
    lat = torch.randn(200, A, L, generator=g) * torch.linspace(0.1, 2.0, L) + 3.0
    full = fit_latent_pca(lat, L)
    lim = 2.0 * full.sigma
    # full rank: points inside the box are unchanged, outside ones land on the box
    inside = full.mean + torch.einsum(
        "nak,alk->nal", (torch.rand(10, A, L, generator=g) * 2 - 1) * 0.99 * lim, full.basis
    )
    torch.testing.assert_close(latent_pca_project(inside, full.mean, full.basis, lim), inside, atol=1e-5, rtol=0)
    far = torch.randn(10, A, L, generator=g) * 20
    c = torch.einsum("nal,alk->nak", latent_pca_project(far, full.mean, full.basis, lim) - full.mean, full.basis)
    assert (c.abs() <= lim + 1e-4).all() and (c.abs() >= lim - 1e-4).any()
    # model outputs live in the K-component box, and K-subspace points inside it are unchanged
    m = model()
    pca = m.fit_latent_statistics(lat)
    mlim = m.latent_limit
    with torch.no_grad():
        m.head.weight.mul_(100)
    pose, rot, trans = seq(N)
    out = m(
        pose[None].expand(4, -1, -1),
        rot[None].expand(4, -1, -1),
        trans[None].expand(4, -1, -1),
        torch.randn(4, A, L) * 5,
    )
    c = torch.einsum("nal,alk->nak", out - pca.mean, pca.basis)
    assert (c.abs() <= mlim + 1e-4).all() and (c.abs() >= mlim - 1e-4).any()
    resid = (out - pca.mean) - torch.einsum("nak,alk->nal", c, pca.basis)
    assert resid.abs().max() < 1e-4  # low-rank projection: nothing outside the K-subspace
    sub = pca.mean + torch.einsum("nak,alk->nal", (torch.rand(10, A, 4, generator=g) * 2 - 1) * 0.99 * mlim, pca.basis)
    torch.testing.assert_close(m.clamp_latents(sub), sub, atol=1e-5, rtol=0)


def test_fit_latent_pca_handles_rank_deficiency():
    lat = torch.randn(3, A, L)  # 3 frames: at most 2 components
    pca = fit_latent_pca(lat, 4)
    assert pca.basis.shape == (A, L, 4) and (pca.sigma[:, 2:] == 0).all() and (pca.basis[:, :, 2:] == 0).all()
    torch.testing.assert_close(
        pca.basis[:, :, :2].transpose(1, 2) @ pca.basis[:, :, :2], torch.eye(2).expand(A, 2, 2), atol=1e-5, rtol=0
    )


def test_initial_latents_zero_until_trained_then_net():
    m = model()
    m.fit_latent_statistics(torch.randn(20, A, L) + 1.0)
    pose, rot, trans = seq(3)
    assert torch.equal(m.init_state(pose[0], rot[0], trans[0]).latents, torch.zeros(A, L))
    m.initial_ready.fill_(True)  # untrained net (zero last layer) -> the clamped train mean
    torch.testing.assert_close(m.init_state(pose[0], rot[0], trans[0]).latents, m.latent_mean, atol=1e-5, rtol=0)
    assert model(initial_net=False).initial is None


def test_untrained_residual_predictor_is_persistence():
    m = model(untrained=True)
    assert m.config.residual
    pose, rot, trans = seq(7)
    init = torch.randn(A, L)
    out = m.rollout(pose, rot, trans, init)
    held = m.clamp_latents(init[None])[0]  # the output clamp is idempotent: the first clamped latents persist
    torch.testing.assert_close(out, held.expand_as(out), atol=1e-5, rtol=1e-5)


def test_no_history_ablation_sees_only_the_current_pose():
    m = model(history=1, velocities=False)
    assert m.feature_dim == 1
    pose, rr, rt = seq(6)
    lat = torch.randn(1, A, L)
    a = m(pose[None, 5:6], rr[None, 5:6], rt[None, 5:6], lat)
    pose2 = pose.clone()
    pose2[:5] += 1.0  # earlier frames never enter
    b = m(pose2[None, 5:6], rr[None, 5:6], rt[None, 5:6], lat)
    torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="history"):
        model(history=2)  # velocities need >= 3


def test_global_latent_pca_projects_onto_a_shared_low_rank_subspace():
    g = torch.Generator().manual_seed(0)
    F = 60
    causes = torch.randn(F, 2, generator=g)  # two causes drive every anchor
    mix = torch.randn(2, A * L, generator=g)
    lat = (causes @ mix).reshape(F, A, L) * 0.5 + 3.0
    m = model(latent_pca="global", latent_pca_components=2, clamp_sigma=10.0)
    m.fit_latent_statistics(lat)
    torch.testing.assert_close(m.clamp_latents(lat), lat, atol=1e-4, rtol=1e-4)  # inside the subspace: unchanged
    off = lat + 0.3 * torch.randn(F, A, L, generator=g)
    err_in, err_out = (m.clamp_latents(off) - lat).pow(2).mean(), (off - lat).pow(2).mean()
    assert err_in < 0.5 * err_out  # noise outside the 2-d subspace is removed
    with pytest.raises(ValueError, match="latent_pca_components"):
        model(latent_pca="global", latent_pca_components=A * L + 1)


def test_zero_latents_are_the_standardised_zero():
    m = model()
    lat = torch.randn(20, A, L) + 2.0
    torch.testing.assert_close(m.zero_latents(), torch.zeros(A, L))  # before the statistics are fit
    m.fit_latent_statistics(lat)
    torch.testing.assert_close(m.zero_latents(), lat.mean(0))
    m.config = dataclasses.replace(m.config, zero_context="raw")
    torch.testing.assert_close(m.zero_latents(), torch.zeros(A, L))


# ----------------------------------------------------------------------------- joint tokens
def joint_model(**kw) -> AppearancePredictor:
    from tests.prep_fixtures import arm_rig

    rig = arm_rig()
    cfg = PredictorConfig(**{**SMALL.to_json(), "joint_tokens": True, **kw})
    torch.manual_seed(0)
    m = AppearancePredictor(cfg, A, [0, 2, 3, 5, 7], rig.pose_dim, seed=0, kinematics=KinematicChain.from_rig(rig))
    with torch.no_grad():
        m.head.weight.copy_(torch.randn(m.head.weight.shape, generator=torch.Generator().manual_seed(3)) * 0.3)
        m.joint_feature_scale.fill_(3.0)  # joint features visibly move the output
    return m.eval()


def joint_seq(T: int, P: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float32)[:, None]
    pose = 0.5 * torch.sin(0.4 * t + torch.rand(1, P, generator=g) * 6)
    rot = 0.3 * torch.randn(T, 3, generator=g)
    trans = torch.randn(T, 3, generator=g) * 0.1
    return pose, rot, trans


def test_kinematic_chain_is_the_rigs_forward_kinematics():
    from gsavatar.geometry.lbs import pose_joints
    from tests.prep_fixtures import arm_rig

    rig = arm_rig()
    chain = KinematicChain(*KinematicChain.from_rig(rig).arrays())  # through its arrays, as from a checkpoint
    pose, rot, trans = joint_seq(6, rig.pose_dim)
    d = lambda x: x.double()  # noqa: E731
    torch.testing.assert_close(
        pose_joints(chain, d(pose), d(rot), d(trans)), pose_joints(rig, d(pose), d(rot), d(trans)), atol=1e-12, rtol=0
    )
    with pytest.raises(ValueError, match="parents must come before"):
        KinematicChain(rig.heads(), [1, 0, 0, 0, 0, 0], *KinematicChain.from_rig(rig).arrays()[2:])


def test_heading_frame_closed_form():
    # upright root facing +X (a +90 degree turn about +Y takes +Z to +X), standing at (2, 0.9, 3)
    R = axis_angle_to_matrix(torch.tensor([[0.0, torch.pi / 2, 0.0]], dtype=torch.float64))  # [1, 3, 3]
    joints = torch.tensor([[[[2.0, 0.9, 3.0], [3.0, 1.5, 3.0], [2.0, 0.9, 2.0]]]], dtype=torch.float64)  # [1,1,3,3]
    q = heading_frame(joints, R)
    # ahead of the root (+X world) becomes +Z, its left (-Z world) +X; heights stay
    expect = torch.tensor([[[[0.0, 0.9, 0.0], [0.0, 1.5, 1.0], [1.0, 0.9, 0.0]]]], dtype=torch.float64)
    torch.testing.assert_close(q, expect, atol=1e-12, rtol=0)
    # lying face down (forward = -Y): the heading comes from the left axis and stays defined
    R2 = axis_angle_to_matrix(torch.tensor([[torch.pi / 2, 0.0, 0.0]], dtype=torch.float64))
    assert torch.isfinite(heading_frame(joints, R2)).all()


def test_joint_tokens_see_gravity_but_not_heading_or_position():
    m = joint_model()
    P = m.pose_dim
    pose, rot, trans = joint_seq(N, P)
    prev = torch.randn(1, A, L)
    head = torch.as_tensor(m.kin_heads[m.root_joint], dtype=torch.float64)
    a = m(pose[None], rot[None], trans[None], prev)

    def moved(Q: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # world' = Q world + c for every point: root rotation Q R, translation Q (head + t) + c - head
        rot2 = matrix_to_axis_angle(Q @ axis_angle_to_matrix(rot.double())).float()
        trans2 = ((head + trans.double()) @ Q.T + c - head).float()
        return rot2, trans2

    yaw = axis_angle_to_matrix(torch.tensor([0.0, 2.1, 0.0], dtype=torch.float64))
    r2, t2 = moved(yaw, torch.tensor([1.5, 0.0, -2.0], dtype=torch.float64))
    torch.testing.assert_close(m(pose[None], r2[None], t2[None], prev), a, atol=1e-4, rtol=0)
    tilt = axis_angle_to_matrix(torch.tensor([0.6, 0.0, 0.0], dtype=torch.float64))  # gravity is not a symmetry
    r3, t3 = moved(tilt, torch.zeros(3, dtype=torch.float64))
    assert (m(pose[None], r3[None], t3[None], prev) - a).abs().max() > 1e-3
    lift = torch.tensor([0.0, 0.4, 0.0], dtype=torch.float64)  # nor is height
    r4, t4 = moved(torch.eye(3, dtype=torch.float64), lift)
    assert (m(pose[None], r4[None], t4[None], prev) - a).abs().max() > 1e-3


def test_joint_token_predictor_rebuilds_from_its_state_dict():
    from gsavatar.models.predictor import KINEMATICS_KEYS

    m = joint_model()
    sd = m.state_dict()
    m2 = AppearancePredictor(
        m.config, A, sd["pose_slots"], m.pose_dim, seed=1, kinematics=tuple(sd[k] for k in KINEMATICS_KEYS)
    )
    m2.load_state_dict(sd)
    pose, rot, trans = joint_seq(9, m.pose_dim, seed=2)
    torch.testing.assert_close(
        m2.eval().rollout(pose, rot, trans, torch.zeros(A, L)),
        m.rollout(pose, rot, trans, torch.zeros(A, L)),
        atol=0,
        rtol=0,
    )
    with pytest.raises(ValueError, match="kinematics"):
        AppearancePredictor(m.config, A, [0], m.pose_dim)


def test_memory_features_against_a_naive_loop_and_closed_forms():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 7, 3, generator=g, dtype=torch.float64)
    taus = (2.0, 5.0)
    f = memory_features(x, taus)
    assert f.shape == (2, 3, 6)
    for b in range(2):
        for s in range(3):
            for i, tau in enumerate(taus):
                w = [torch.exp(torch.tensor(-k / tau, dtype=torch.float64)) for k in range(7)]  # k frames back
                val = sum(w[k] * x[b, 6 - k, s] for k in range(7)) / sum(w)
                d = [x[b, 6 - k, s] - x[b, 5 - k, s] for k in range(6)]
                spd = sum(w[k] * abs(d[k]) for k in range(6)) / sum(w[:6])
                vel = sum(w[k] * d[k] for k in range(6)) / sum(w[:6])
                torch.testing.assert_close(f[b, s, 3 * i : 3 * i + 3], torch.stack([val, spd, vel]))
    # a stationary past (a sequence start repeats its first frame): the value, no speed, no velocity
    c = memory_features(torch.full((1, 9, 1), 0.7), (4.0,))[0, 0]
    torch.testing.assert_close(c, torch.tensor([0.7, 0.0, 0.0]))
    # a ramp of slope 0.25 per frame: speed and velocity are the slope
    r = memory_features((0.25 * torch.arange(9.0))[None, :, None], (4.0,))[0, 0]
    torch.testing.assert_close(r[1:], torch.tensor([0.25, 0.25]))


def test_memory_timescales_widen_the_window_and_keep_streaming_exact():
    m = model(memory_timescales=(2.0, 3.0))
    W = m.config.window_frames
    assert W == 9 and m.feature_dim == 3 * N - 3 + 6
    pose, rot, trans = seq(14)
    init = torch.randn(A, L)
    roll = m.rollout(pose, rot, trans, init)
    prev, ref = init[None], []
    for t in range(14):
        idx = torch.clamp(torch.arange(t - W + 1, t + 1), min=0)
        prev = m(pose[idx][None], rot[idx][None], trans[idx][None], prev)
        ref.append(prev[0])
    torch.testing.assert_close(torch.stack(ref), roll, atol=1e-5, rtol=1e-5)
    # causal, and a frame W - 1 back still matters (N_b alone would not see it)
    t = 12
    p2 = pose.clone()
    p2[t - W + 1] += 0.7
    idx = torch.clamp(torch.arange(t - W + 1, t + 1), min=0)
    a = m(pose[idx][None], rot[idx][None], trans[idx][None], init[None])
    b = m(p2[idx][None], rot[idx][None], trans[idx][None], init[None])
    assert not torch.allclose(a, b)
    with pytest.raises(ValueError, match="memory_timescales"):
        model(memory_timescales=(0.0,))
