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
    joint_speeds,
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


def test_world_orientation_gives_the_transformer_the_roots_world_orientation_slots():
    """``world_orientation``: six more slots, the rotation matrix's first two columns over the window (naive form);
    a turn of the whole motion now changes the prediction (the model without it is invariant, test above)."""
    from gsavatar.models.predictor import orientation_features

    m = model(world_orientation=True)
    base = model()
    assert m.num_slots == base.num_slots + 6 and m.pose_tokens.num_anchors == m.num_slots
    pose, rot, trans = seq(N)
    x = m.slot_values(pose[None], rot[None], trans[None])[0]  # [N, S]
    torch.testing.assert_close(x[:, : base.num_slots], base.slot_values(pose[None], rot[None], trans[None])[0])
    for k in range(N):
        R = axis_angle_to_matrix(rot[k].double())
        torch.testing.assert_close(x[k, -6:].double(), torch.cat([R[:, 0], R[:, 1]]), atol=1e-6, rtol=0)
    torch.testing.assert_close(x[:, -6:], orientation_features(rot))
    Q = random_rotation(torch.Generator().manual_seed(3))
    rot2 = matrix_to_axis_angle(Q @ axis_angle_to_matrix(rot.double())).float()
    prev = torch.randn(1, A, L)
    a, b = m(pose[None], rot[None], trans[None], prev), m(pose[None], rot2[None], trans[None], prev)
    assert (a - b).abs().max() > 1e-3


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


def test_joint_speeds_against_a_naive_loop_and_a_closed_form():
    g = torch.Generator().manual_seed(4)
    q = torch.randn(2, 5, 3, 3, generator=g, dtype=torch.float64)  # [B, N, J, 3]
    sp = joint_speeds(q, root=1)
    assert sp.shape == (2, 3, 4)
    for b in range(2):
        for j in range(3):
            for k in range(1, 5):
                r_now, r_before = q[b, k, j] - q[b, k, 1], q[b, k - 1, j] - q[b, k - 1, 1]
                torch.testing.assert_close(sp[b, j, k - 1], torch.linalg.norm(r_now - r_before))
    assert sp[:, 1].abs().max() == 0  # the root does not move relative to itself
    # a joint gliding at a constant velocity while the whole body translates: its speed is |v| in every pair
    t = torch.arange(6, dtype=torch.float64)[:, None]
    body = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64) * t  # the root's (and everything's) drift
    v = torch.tensor([0.03, 0.04, 0.0], dtype=torch.float64)  # |v| = 0.05 per frame
    glide = torch.stack([body, body + v * t + 1.0], 1)[None]  # [1, 6, 2, 3]
    torch.testing.assert_close(joint_speeds(glide, 0)[0, 1], torch.full((5,), 0.05, dtype=torch.float64))


def test_joint_speed_tokens_are_the_positions_speeds_and_keep_the_symmetries():
    m = joint_model(joint_speeds=True)
    base = joint_model()
    pose, rot, trans = joint_seq(N, m.pose_dim)
    f = m.joint_features(pose[None], rot[None], trans[None])
    f0 = base.joint_features(pose[None], rot[None], trans[None])
    assert f.shape == (1, m.num_joints, m.joint_feature_dim) and m.joint_feature_dim == f0.shape[-1] + N - 1
    torch.testing.assert_close(f[..., : f0.shape[-1]], f0)  # the position blocks are unchanged
    # the speeds from the positions the joint tokens see (forward kinematics of the rig, world frame): the heading
    # frame is one rotation for the window, so they are world speeds relative to the root
    from gsavatar.geometry.lbs import pose_joints
    from tests.prep_fixtures import arm_rig

    world = pose_joints(arm_rig(), pose.double(), rot.double(), trans.double())[None]  # [1, N, J, 3]
    torch.testing.assert_close(f[..., f0.shape[-1] :].double(), joint_speeds(world, m.root_joint), atol=1e-5, rtol=0)
    prev = torch.randn(1, A, L)
    with torch.no_grad():
        m.joint_feature_scale.fill_(3.0)
    a = m(pose[None], rot[None], trans[None], prev)
    yaw = axis_angle_to_matrix(torch.tensor([0.0, -1.2, 0.0], dtype=torch.float64))
    head = torch.as_tensor(m.kin_heads[m.root_joint], dtype=torch.float64)
    rot2 = matrix_to_axis_angle(yaw @ axis_angle_to_matrix(rot.double())).float()
    trans2 = ((head + trans.double()) @ yaw.T + torch.tensor([0.7, 0.0, 1.1], dtype=torch.float64) - head).float()
    torch.testing.assert_close(m(pose[None], rot2[None], trans2[None], prev), a, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="joint_speeds needs config.joint_tokens"):
        AppearancePredictor(PredictorConfig(**{**SMALL.to_json(), "joint_speeds": True}), A, [0], P)


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


def gated_model(**kw) -> AppearancePredictor:
    """A gated predictor with visibly input-dependent candidate and gate."""
    m = model(untrained=True, gate=True, **kw)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        m.head.weight.copy_(torch.randn(m.head.weight.shape, generator=g) * 0.3)
        m.gate_head.weight.copy_(torch.randn(m.gate_head.weight.shape, generator=g) * 0.5)
        m.gate_head.bias.zero_()
    return m


def test_gated_update_is_a_convex_step_toward_the_candidate():
    m = gated_model()
    m.fit_latent_statistics(torch.randn(30, A, L, generator=torch.Generator().manual_seed(1)) * 2.0 + 0.5)
    m.latent_pca_ready.fill_(False)  # no clamp: the update itself
    pose, rot, trans = seq(6)
    prev = torch.randn(2, A, L) * 2.0
    win = [windows(x, 5).expand(2, -1, -1) for x in (pose, rot, trans)]
    out = m(*win, prev)
    # the same forward by hand: tokens -> anchor tokens -> gate and candidate -> l + g (c - l)
    x, _ = m.input_features(*win)
    x = (x - m.feature_mean) * m.feature_scale
    lat = (prev - m.latent_mean) / m.latent_scale
    tok = torch.cat([m.pose_tokens(x) + m.type_embedding[0], m.latent_tokens(lat) + m.type_embedding[1]], 1)
    h = m.norm(m.transformer(tok + m.positional))[:, m.num_slots :]
    g, c = torch.sigmoid(m.gate_head(h)).detach(), (m.latent_mean + m.latent_scale * m.head(h)).detach()
    assert 0 < float(g.min()) and float(g.max()) < 1
    torch.testing.assert_close(out, prev + g * (c - prev), atol=1e-5, rtol=1e-5)
    # each (anchor, dim) lands between its previous value and its candidate
    lo, hi = torch.minimum(prev, c), torch.maximum(prev, c)
    assert bool(((out >= lo - 1e-5) & (out <= hi + 1e-5)).all())


def test_untrained_gated_predictor_starts_near_persistence():
    m = model(untrained=True, gate=True)
    pose, rot, trans = seq(4)
    prev = torch.randn(1, A, L)
    out = m(windows(pose, 3), windows(rot, 3), windows(trans, 3), prev)
    step = (out - prev).detach().abs().max()
    assert 0 < float(step) < 0.05 * float((prev - m.latent_mean).abs().max() + 1.0)


def test_gate_without_latent_tokens_is_affine_in_the_previous_latents():
    m = gated_model(latent_tokens=False)
    assert not any(k.startswith("latent_tokens.") for k in m.state_dict())  # no token of the previous latents
    pose, rot, trans = seq(6)
    win = [windows(x, 5) for x in (pose, rot, trans)]
    g = torch.Generator().manual_seed(2)
    p1, p2 = torch.randn(1, A, L, generator=g), torch.randn(1, A, L, generator=g)
    f = lambda p: m(*win, p)  # noqa: E731  (clamp not fit yet: the update alone)
    for w in (0.0, 0.3, 1.7):
        torch.testing.assert_close(f(w * p1 + (1 - w) * p2), w * f(p1) + (1 - w) * f(p2), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(f(p1), f(p2))  # the previous latents still matter, through the gate
    # causality and streaming are those of any predictor
    init = torch.randn(A, L)
    outs, st = [], m.init_state(pose[0], rot[0], trans[0], init)
    for t in range(6):
        lat, st = m.step(st, pose[t], rot[t], trans[t])
        outs.append(lat)
    assert torch.equal(torch.stack(outs), m.rollout(pose, rot, trans, init))
    rebuilt = AppearancePredictor(m.config, A, [0, 2, 3, 5, 7], P)
    rebuilt.load_state_dict(m.state_dict())
    assert torch.equal(rebuilt.eval()(*win, p1), f(p1))


def test_gate_options_are_validated():
    with pytest.raises(ValueError, match="config.gate needs config.residual"):
        model(gate=True, residual=False)
    with pytest.raises(ValueError, match="latent_tokens=False needs config.gate"):
        model(latent_tokens=False)


def test_signal_features_against_a_naive_loop_and_closed_forms():
    from gsavatar.models.predictor import SIGNAL_KINDS, signal_features

    assert SIGNAL_KINDS == ("speed", "height", "vertical_velocity", "vertical_acceleration")
    g = torch.Generator().manual_seed(6)
    q = torch.randn(2, 5, 3, 3, generator=g, dtype=torch.float64)  # [B, N, J, 3]
    f = signal_features(q, root=1)
    assert f.shape == (2, 3, 4, 5)
    for b in range(2):
        for j in range(3):
            for k in range(5):
                y = lambda kk: q[b, kk, j, 1]  # noqa: E731
                assert float(f[b, j, 1, k]) == pytest.approx(float(q[b, k, j, 1] - q[b, k, 1, 1]), abs=1e-12)
                if k >= 1:
                    rel = (q[b, k, j] - q[b, k, 1]) - (q[b, k - 1, j] - q[b, k - 1, 1])
                    assert float(f[b, j, 0, k]) == pytest.approx(float(torch.linalg.norm(rel)), abs=1e-12)
                    assert float(f[b, j, 2, k]) == pytest.approx(float(y(k) - y(k - 1)), abs=1e-12)
                if k >= 2:
                    assert float(f[b, j, 3, k]) == pytest.approx(float(y(k) - 2 * y(k - 1) + y(k - 2)), abs=1e-12)
    assert f[:, :, 0, 0].abs().max() == 0 and f[:, :, 2, 0].abs().max() == 0 and f[:, :, 3, :2].abs().max() == 0
    # a ball thrown upward (y = v t - a t^2 / 2 per frame) beside a resting root: constant acceleration -a,
    # vertical velocity v - a (k - 1/2), speed |vertical velocity|
    t = torch.arange(6, dtype=torch.float64)
    ball = torch.stack([torch.zeros(6), 0.3 * t - 0.02 * t * t, torch.zeros(6)], -1)
    q2 = torch.stack([torch.zeros(6, 3, dtype=torch.float64), ball], 1)[None]  # [1, 6, 2, 3]
    s = signal_features(q2, root=0)[0, 1]
    torch.testing.assert_close(s[3, 2:], torch.full((4,), -0.04, dtype=torch.float64))
    torch.testing.assert_close(s[2, 1:], 0.3 - 0.04 * (t[1:] - 0.5))
    torch.testing.assert_close(s[0, 1:], s[2, 1:].abs())
    torch.testing.assert_close(s[1], ball[:, 1])


def signal_model(**kw) -> AppearancePredictor:
    """A signal-readout predictor with fitted statistics and visibly input-dependent gate and candidate."""
    from tests.prep_fixtures import arm_rig

    rig = arm_rig()
    cfg = PredictorConfig(
        **{**SMALL.to_json(), "readout": "signals", "latent_pca": "global", "signal_heads": 2, "signal_hidden": 8, **kw}
    )
    m = AppearancePredictor(cfg, A, [0, 2, 3, 5, 7], rig.pose_dim, seed=0, kinematics=KinematicChain.from_rig(rig))
    g = torch.Generator().manual_seed(8)
    pose, rot, trans = joint_seq(40, rig.pose_dim, seed=1)
    win = torch.clamp(torch.arange(40)[:, None] + torch.arange(-N + 1, 1), min=0)  # [40, N]
    feats = m.input_features(pose[win], rot[win], trans[win])
    m.fit_input_normalization(*feats)
    m.fit_latent_statistics(torch.randn(40, A, L, generator=g) * 1.5 + 0.3)
    if hasattr(m, "signal_out"):
        with torch.no_grad():
            m.signal_out.weight.copy_(torch.randn(m.signal_out.weight.shape, generator=g))
            m.signal_out.bias.zero_()
    return m.eval()


def test_signal_readout_is_a_gated_step_of_the_global_pca_coefficients():
    m = signal_model()
    K = m.config.latent_pca_components
    pose, rot, trans = joint_seq(N, m.pose_dim, seed=3)
    prev = m.clamp_latents(torch.randn(1, A, L, generator=torch.Generator().manual_seed(4)))
    out = m(pose[None], rot[None], trans[None], prev)
    # by hand: standardised signal tokens -> shared MLP -> selections -> gate, candidate -> z + g (c - z)
    raw = m.joint_features(pose[None], rot[None], trans[None])
    sig = ((raw - m.joint_feature_mean) * m.joint_feature_scale).reshape(1, -1, N)
    kinds = torch.eye(4).repeat(m.num_joints, 1)[None]
    emb = m.signal_mlp(torch.cat([sig, kinds], -1))[0]  # [J*4, H]
    pooled = torch.softmax(m.selection_logits, -1) @ emb  # [heads, H]
    o = m.signal_out(pooled.reshape(1, -1))[0]
    c, gate = o[:K], torch.sigmoid(o[K:])
    z = ((prev - m.latent_mean) / m.latent_scale).flatten() @ m.global_basis
    z = z + gate * (c - z)
    ref = m.clamp_latents(m.latent_mean + m.latent_scale * (m.global_basis @ z).reshape(A, L))
    torch.testing.assert_close(out[0], ref.detach(), atol=1e-5, rtol=1e-5)
    # affine in the previous coefficients: a convex mix of two contexts gives the same mix of the answers
    # (inside the clamp box, where the clamp is the identity on the subspace)
    p2 = m.clamp_latents(prev + 0.05 * torch.randn(1, A, L, generator=torch.Generator().manual_seed(5)))
    mix = m(pose[None], rot[None], trans[None], 0.5 * prev + 0.5 * p2)
    both = 0.5 * out + 0.5 * m(pose[None], rot[None], trans[None], p2)
    torch.testing.assert_close(mix, both, atol=1e-5, rtol=1e-5)


def test_a_peaked_selection_reads_only_the_selected_joint_and_kind():
    from tests.prep_fixtures import arm_rig

    m = signal_model()
    with torch.no_grad():  # every head selects the height of joint 3 (LeftForeArm of the chain Hips..LeftFinger)
        m.selection_logits.fill_(-1e4)
        m.selection_logits[:, 3 * 4 + 1] = 0.0
    slots = arm_rig().slot_joints()
    pose, rot, trans = joint_seq(N, m.pose_dim, seed=3)
    prev = m.latent_mean[None].clone()
    a = m(pose[None], rot[None], trans[None], prev)

    def turned(joint: int) -> torch.Tensor:
        p2 = pose.clone()
        p2[:, slots == joint] += 0.4
        return m(p2[None], rot[None], trans[None], prev)

    torch.testing.assert_close(turned(4), a, atol=1e-6, rtol=0)  # the hand's rotation moves only the finger
    torch.testing.assert_close(turned(3), a, atol=1e-6, rtol=0)  # its own rotation moves its children, not it
    assert (turned(2) - a).abs().max() > 1e-3  # the upper arm's rotation moves the forearm's head
    # turning and moving the whole motion about +Y keeps every signal
    yaw = axis_angle_to_matrix(torch.tensor([0.0, 1.3, 0.0], dtype=torch.float64))
    head = torch.as_tensor(m.kin_heads[m.root_joint], dtype=torch.float64)
    rot2 = matrix_to_axis_angle(yaw @ axis_angle_to_matrix(rot.double())).float()
    trans2 = ((head + trans.double()) @ yaw.T + torch.tensor([0.4, 0.0, -0.9], dtype=torch.float64) - head).float()
    torch.testing.assert_close(m(pose[None], rot2[None], trans2[None], prev), a, atol=1e-4, rtol=0)


def test_signal_predictor_streams_and_rebuilds_from_its_state_dict():
    from gsavatar.models.predictor import KINEMATICS_KEYS

    m = signal_model()
    pose, rot, trans = joint_seq(9, m.pose_dim, seed=2)
    init = m.latent_mean.clone()
    st, outs = m.init_state(pose[0], rot[0], trans[0], init), []
    for t in range(9):
        lat, st = m.step(st, pose[t], rot[t], trans[t])
        outs.append(lat)
    ref = m.rollout(pose, rot, trans, init)
    assert torch.equal(torch.stack(outs), ref)
    sd = m.state_dict()
    m2 = AppearancePredictor(
        m.config, A, sd["pose_slots"], m.pose_dim, seed=1, kinematics=tuple(sd[k] for k in KINEMATICS_KEYS)
    )
    m2.load_state_dict(sd)
    assert torch.equal(m2.eval().rollout(pose, rot, trans, init), ref)


def test_signal_readout_options_are_validated_and_its_logits_train_faster():
    from gsavatar.models.predictor import SELECTION_LR_SCALE
    from gsavatar.train.predictor import optimizer_groups
    from tests.prep_fixtures import arm_rig

    kin = KinematicChain.from_rig(arm_rig())
    P2 = kin.pose_dim
    base = {**SMALL.to_json(), "readout": "signals", "latent_pca": "global"}
    with pytest.raises(ValueError, match="latent_pca='global'"):
        AppearancePredictor(PredictorConfig(**{**base, "latent_pca": "anchor"}), A, [0], P2, kinematics=kin)
    with pytest.raises(ValueError, match="joint_tokens, memory_timescales cannot"):
        AppearancePredictor(PredictorConfig(**{**base, "joint_tokens": True}), A, [0], P2, kinematics=kin)
    with pytest.raises(ValueError, match="readout='signals' needs the rig's kinematics"):
        AppearancePredictor(PredictorConfig(**base), A, [0], P2)
    with pytest.raises(ValueError, match="gate and latent_tokens shape the transformer"):
        AppearancePredictor(PredictorConfig(**{**base, "gate": True}), A, [0], P2, kinematics=kin)
    with pytest.raises(ValueError, match="signal_pose_path is for readout='signals'"):
        AppearancePredictor(PredictorConfig(**{**base, "readout": "transformer", "signal_pose_path": True}), A, [0], P2)
    unfit = AppearancePredictor(PredictorConfig(**base), A, [0, 1], P2, kinematics=kin)  # no latent PCA yet
    pose, rot, trans = joint_seq(N, P2)
    prev = torch.randn(1, A, L)
    assert torch.equal(unfit(pose[None], rot[None], trans[None], prev), prev)  # nothing to update: persistence
    with pytest.raises(ValueError, match="config.readout must be"):
        AppearancePredictor(PredictorConfig(**{**base, "readout": "mlp"}), A, [0], P2, kinematics=kin)
    m = signal_model()
    with pytest.raises(ValueError, match="feature_noise"):
        pose, rot, trans = joint_seq(N, m.pose_dim)
        m(pose[None], rot[None], trans[None], m.latent_mean[None], torch.zeros(1, m.num_slots, m.feature_dim))
    groups = optimizer_groups(m, 1e-3)
    assert len(groups) == 2 and groups[1]["params"] == [m.selection_logits]
    assert groups[1]["lr"] == pytest.approx(1e-3 * SELECTION_LR_SCALE) and groups[1]["weight_decay"] == 0.0
    assert sum(p.numel() for g in groups for p in g["params"]) == sum(p.numel() for p in m.parameters())
    assert len(optimizer_groups(model(), 1e-3)) == 1  # the transformer: one group, as its checkpoints hold


def test_signal_readout_without_history_sees_the_current_heights_only():
    m = signal_model(history=1, velocities=False)
    assert m.joint_feature_dim == 4
    pose, rot, trans = joint_seq(5, m.pose_dim, seed=3)
    f = m.joint_features(pose[None, -1:], rot[None, -1:], trans[None, -1:])  # [1, J, 4]
    assert f[..., [0, 2, 3]].abs().max() == 0 and f[..., 1].abs().max() > 0
    prev = m.latent_mean[None].clone()
    a = m(pose[None, -1:], rot[None, -1:], trans[None, -1:], prev)
    b = m(pose[None, -1:], rot[None, -1:], trans[None, -1:] + 0.3, prev)  # lifted whole: heights above the root
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


def test_signal_pose_path_adds_the_current_poses_part_and_feeds_back_the_state():
    m = signal_model(signal_pose_path=True)
    K = m.config.latent_pca_components
    g = torch.Generator().manual_seed(9)
    with torch.no_grad():
        m.signal_pose[-1].weight.copy_(torch.randn(m.signal_pose[-1].weight.shape, generator=g))
    pose, rot, trans = joint_seq(N + 1, m.pose_dim, seed=4)
    p = lambda f: m.signal_pose(m.initial_features(pose[f : f + 1]))[0].detach()  # noqa: E731  [K]
    coef = lambda lat: ((lat - m.latent_mean) / m.latent_scale).flatten() @ m.global_basis  # noqa: E731
    base = signal_model()  # the same weights but the pose path: z_t = z_{t-1} + g (c - z_{t-1})
    base.load_state_dict({k: v for k, v in m.state_dict().items() if not k.startswith("signal_pose.")})
    prev = m.clamp_latents(m.latent_mean + 0.2 * torch.randn(A, L, generator=g))
    z_prev = coef(prev) - p(N - 2)  # the state under frame t-1's instantaneous part
    # the gated step from the state the base model would get as its whole previous coefficients
    prev_state = m.latent_mean + m.latent_scale * (m.global_basis @ z_prev).reshape(A, L)
    step = coef(base(pose[None, :N], rot[None, :N], trans[None, :N], prev_state[None])[0])
    out = m(pose[None, :N], rot[None, :N], trans[None, :N], prev[None])[0]
    torch.testing.assert_close(coef(out), step + p(N - 1), atol=1e-4, rtol=1e-4)
    assert (p(N - 1) - p(N - 2)).abs().max() > 1e-3 and K == p(0).numel()


def test_orientation_features_are_the_rotation_matrix_columns():
    from gsavatar.models.predictor import orientation_features

    g = torch.Generator().manual_seed(2)
    aa = torch.randn(7, 3, generator=g, dtype=torch.float64)
    R = axis_angle_to_matrix(aa)
    f = orientation_features(aa)
    for b in range(7):  # naive: column 0 then column 1
        torch.testing.assert_close(f[b], torch.cat([R[b, :, 0], R[b, :, 1]]))
    yaw = torch.tensor([[0.0, 1.2, 0.0]], dtype=torch.float64)  # a turn about +Y moves the facing columns
    assert (orientation_features(yaw) - orientation_features(torch.zeros(1, 3, dtype=torch.float64))).abs().max() > 0.5


def test_world_orientation_makes_the_pose_path_see_which_way_the_body_faces():
    """Every other input of the signal readout is in the heading frame (a yaw of the whole motion changes nothing);
    with ``world_orientation`` the pose path reads the root's world orientation, as its naive form says."""
    from gsavatar.models.predictor import orientation_features

    m = signal_model(signal_pose_path=True, world_orientation=True)
    g = torch.Generator().manual_seed(9)
    with torch.no_grad():
        m.signal_pose[-1].weight.copy_(torch.randn(m.signal_pose[-1].weight.shape, generator=g))
    pose, rot, trans = joint_seq(N, m.pose_dim, seed=4)
    yawed = matrix_to_axis_angle(axis_angle_to_matrix(torch.tensor([0.0, 1.0, 0.0])) @ axis_angle_to_matrix(rot))
    prev = m.latent_mean[None].clone()
    a = m(pose[None], rot[None], trans[None], prev)[0]
    b = m(pose[None], yawed[None], trans[None], prev)[0]
    assert (a - b).abs().max() > 1e-3  # the turn shows
    coef = lambda lat: ((lat - m.latent_mean) / m.latent_scale).flatten() @ m.global_basis  # noqa: E731
    p = (
        lambda r, f: m.signal_pose(  # noqa: E731  naive instantaneous part of frame f  [K]
            torch.cat([m.initial_features(pose[f : f + 1]), orientation_features(r[f : f + 1])], -1)
        )[0].detach()
    )
    base = signal_model()  # the same weights but the pose path: blind to the turn
    base.load_state_dict({k: v for k, v in m.state_dict().items() if not k.startswith("signal_pose.")})
    torch.testing.assert_close(
        base(pose[None], rot[None], trans[None], prev),
        base(pose[None], yawed[None], trans[None], prev),
        atol=1e-5,
        rtol=0,
    )
    for r, out in ((rot, a), (yawed, b)):  # y_t = gated step of z_{t-1} = y_{t-1} - p_{t-1}, plus p_t
        z_prev = coef(prev[0]) - p(r, N - 2)
        prev_state = m.latent_mean + m.latent_scale * (m.global_basis @ z_prev).reshape(A, L)
        step = coef(base(pose[None], r[None], trans[None], prev_state[None])[0])
        torch.testing.assert_close(coef(out), step + p(r, N - 1), atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="world_orientation with readout=.signals. is an input of its pose path"):
        signal_model(world_orientation=True)


def test_both_readouts_gate_the_transformers_answer_toward_the_signals_candidate():
    m = signal_model(readout="both")
    tr = signal_model(readout="transformer", joint_tokens=False)  # the same transformer weights, no signals
    tr.load_state_dict({k: v for k, v in m.state_dict().items() if k in tr.state_dict()}, strict=True)
    with torch.no_grad():
        m.head.weight.copy_(torch.randn(m.head.weight.shape, generator=torch.Generator().manual_seed(3)) * 0.3)
        tr.head.weight.copy_(m.head.weight)
    pose, rot, trans = joint_seq(N, m.pose_dim, seed=5)
    prev = m.clamp_latents(m.latent_mean + 0.3 * torch.randn(1, A, L, generator=torch.Generator().manual_seed(6)))
    args = (pose[None], rot[None], trans[None], prev)
    K = m.config.latent_pca_components
    with torch.no_grad():
        m.signal_out.bias[K:].fill_(-1e4)  # shut: the transformer's answer
    torch.testing.assert_close(m(*args), tr(*args), atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        m.signal_out.bias[K:].fill_(1e4)  # open: the signals' candidate, whatever the transformer said
        m.head.weight.mul_(3.0)
    cand = m.signal_out(
        torch.einsum(
            "ht,td->hd",
            torch.softmax(m.selection_logits, -1),
            m.signal_mlp(
                torch.cat(
                    [
                        ((m.joint_features(*args[:3]) - m.joint_feature_mean) * m.joint_feature_scale).reshape(-1, N),
                        torch.eye(4).repeat(m.num_joints, 1),
                    ],
                    -1,
                )
            ),
        ).reshape(1, -1)
    )[0, :K].detach()
    ref = m.clamp_latents(m.latent_mean + m.latent_scale * (m.global_basis @ cand).reshape(A, L))
    torch.testing.assert_close(m(*args)[0], ref, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="signal_pose_path is for readout='signals'"):
        signal_model(readout="both", signal_pose_path=True)
