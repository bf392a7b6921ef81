"""The RS essential matrix and its Sampson error: Jacobian, ground truth, GS limit."""

import numpy as np
from conftest import TOL

from rsvo_ros.core.geometry import pose_at_row, so3_exp
from rsvo_ros.twoview.reference import rs_depths, sampson_residuals
from rsvo_ros.twoview.state import Correspondences, RSBatch, make_correspondences


def _random_problem(rng, n=60, batch=3):
    corr = Correspondences(
        np.column_stack([0.4 * rng.normal(size=(n, 2)), np.ones(n)]),
        np.column_stack([0.4 * rng.normal(size=(n, 2)), np.ones(n)]),
        rng.uniform(-0.02, 0.02, n), rng.uniform(-0.02, 0.02, n), 1000.0,
        ds_dy=1000.0 * 50e-6,  # f_y tau: the row-aware Sampson error
    )
    R = np.stack([so3_exp(0.2 * rng.normal(size=3)) for _ in range(batch)])
    vel = rng.normal(size=(batch, 12)) * np.repeat([2.0, 30.0, 2.0, 30.0], 3)
    return corr, RSBatch.from_pose(R, rng.normal(size=(batch, 3)), vel)


def test_analytic_jacobian_matches_finite_differences(rng):
    corr, state = _random_problem(rng)
    _, J = sampson_residuals(state, corr, jacobian=True)
    h = 1e-6
    J_fd = np.zeros_like(J)
    for k in range(17):
        d = np.zeros((len(state), 17))
        d[:, k] = h
        e_plus, _ = sampson_residuals(state.retract(d), corr)
        e_minus, _ = sampson_residuals(state.retract(-d), corr)
        J_fd[..., k] = (e_plus - e_minus) / (2 * h)
    scale = np.abs(J_fd).max(axis=(0, 1)) + 1e-12
    assert (np.abs(J - J_fd).max(axis=(0, 1)) / scale).max() < TOL["jacobian_rel"]


def test_jacobian_on_index_subsets_matches_full(rng):
    corr, state = _random_problem(rng, batch=2)
    idx = np.stack([rng.permutation(len(corr))[:20] for _ in range(2)])
    e_sub, J_sub = sampson_residuals(state, corr, jacobian=True, idx=idx)
    e_all, J_all = sampson_residuals(state, corr, jacobian=True)
    for b in range(2):
        assert np.allclose(e_sub[b], e_all[b, idx[b]])
        assert np.allclose(J_sub[b], J_all[b, idx[b]])


def test_ground_truth_parameters_give_zero_residual(paper_scene):
    pair = paper_scene.frame_pair(np.random.default_rng(3), level=6)
    row_ref = pair.K[1, 2]
    R_m, t_m, (w_p, v_p, w_c, v_c) = pose_at_row(pair.R, pair.t, pair.w_prev, pair.v_prev,
                                                 pair.w_curr, pair.v_curr, row_ref,
                                                 pair.line_delay)
    s = np.linalg.norm(t_m)
    state = RSBatch.from_pose(R_m, t_m, np.concatenate([w_p, v_p / s, w_c, v_c / s]))
    corr = make_correspondences(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay, row_ref)
    e, _ = sampson_residuals(state, corr)
    assert np.abs(e).max() < TOL["gt_residual_px"]
    # and the points are in front of both cameras
    lam_p, lam_c = rs_depths(state, corr)
    assert np.all(lam_p > 0) and np.all(lam_c > 0)


def test_zero_velocity_model_is_the_gs_sampson_error(rng):
    corr, state = _random_problem(rng, batch=1)
    state.vel[:] = 0.0
    e_rs, _ = sampson_residuals(state, corr)
    R, t = state.R[0], state.t[0]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    Ex = corr.x_prev @ E.T
    ETx = corr.x_curr @ E
    num = np.einsum("ni,ni->n", corr.x_curr, Ex)
    e_gs = 1000.0 * num / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + ETx[:, 0] ** 2
                                  + ETx[:, 1] ** 2)
    assert np.allclose(e_rs[0], e_gs, atol=1e-9)


def test_sign_flip_of_translation_and_velocities_keeps_the_residual(rng):
    corr, state = _random_problem(rng, batch=1)
    flipped = RSBatch(state.R, -state.t, state.vel * np.repeat([1, -1, 1, -1], 3))
    e1, _ = sampson_residuals(state, corr)
    e2, _ = sampson_residuals(flipped, corr)
    assert np.allclose(np.abs(e1), np.abs(e2))


def test_compiled_kernel_equals_the_numpy_model(rng):
    """rs_kernels evaluates the same residuals and Jacobian as the numpy specification."""
    from rsvo_ros.twoview import kernels as rs_kernels
    from rsvo_ros.twoview.solver import depths, residuals

    corr, state = _random_problem(rng)
    e, J = sampson_residuals(state, corr, jacobian=True)
    assert np.allclose(residuals(state, corr), e, rtol=0,
                       atol=TOL["kernel_vs_numpy"] * np.abs(e).max())
    for got, want in zip(depths(state, corr), rs_depths(state, corr), strict=True):
        assert np.allclose(got, want, rtol=TOL["kernel_vs_numpy"], atol=0)
    for b in range(len(state)):
        e_b, J_b = rs_kernels.residuals_and_jacobian(state.R[b], state.t[b], state.vel[b],
                                                     corr.x_prev, corr.x_curr, corr.s_prev,
                                                     corr.s_curr, (corr.focal, corr.ds_dy))
        assert np.allclose(e_b, e[b], rtol=0, atol=TOL["kernel_vs_numpy"] * np.abs(e).max())
        assert np.allclose(J_b, J[b], rtol=0, atol=TOL["kernel_vs_numpy"] * np.abs(J).max())


def test_the_gs_models_fast_path_gives_the_general_kernels_bits(rng):
    """Zero velocities with steps in rotation and translation only (the null model's refits)
    take a shorter path through the kernel: the same cost and normal equations, to the bit, as
    the general 17-DOF evaluation; velocities that are not zero keep the general path."""
    from rsvo_ros.twoview import kernels as rs_kernels
    from rsvo_ros.twoview.solver import levenberg_marquardt

    corr, state = _random_problem(rng, batch=2)
    state.vel[:] = 0.0
    args = (corr.x_prev, corr.x_curr, corr.s_prev, corr.s_curr, (corr.focal, corr.ds_dy),
            np.arange(len(corr)), 2.0, np.zeros(12), np.zeros(12))
    for b in range(2):
        out = {}
        for gs in (False, True):
            H, g = np.full((17, 17), np.nan), np.full(17, np.nan)
            cost = rs_kernels._normal_equations(state.R[b], state.t[b], state.vel[b], *args,
                                                H, g, gs)
            out[gs] = cost, H, g
        assert out[True][0] == out[False][0]
        assert np.array_equal(out[True][1][:5, :5], out[False][1][:5, :5])
        assert np.array_equal(out[True][2][:5], out[False][2][:5])
        assert not out[True][1][5:].any() and not out[True][2][5:].any()
    basis = np.eye(17)[:, :5]
    assert rs_kernels._is_gs(basis, state.vel[0])
    assert not rs_kernels._is_gs(basis, state.vel[0] + 1e-9)
    assert not rs_kernels._is_gs(np.eye(17)[:, :6], state.vel[0])
    # residuals and depths of the GS model take the short path too: the general one's bits
    Rr = tuple(tuple(r) for r in state.R[0])
    tt, V = tuple(state.t[0]), ((0.0,) * 3,) * 4
    e_fast = rs_kernels.residuals_serial(state.R[:1], state.t[:1], state.vel[:1], *args[:5])
    lam_fast = rs_kernels.depths_batch(state.R[:1], state.t[:1], state.vel[:1], *args[:4])
    for i in range(len(corr)):
        xp, xc = tuple(corr.x_prev[i]), tuple(corr.x_curr[i])
        si, ci = corr.s_prev[i], corr.s_curr[i]
        assert e_fast[0, i] == rs_kernels._residual(Rr, tt, V, xp, xc, si, ci, args[4])
        _, _, _, _, _, a, bb, _, T = rs_kernels._rays(Rr, tt, V, xp, xc, si, ci)
        assert (a, bb, T) == (rs_kernels._mv(Rr, xp), xc, tt)  # what depths_batch uses
    assert np.isfinite(lam_fast[0]).all()
    # the whole LM on that path keeps the velocities at zero and moves the pose
    fast, cost_fast, _ = levenberg_marquardt(state, corr, 10, robust_scale=2.0, basis=basis)
    assert np.isfinite(cost_fast).all() and not fast.vel.any()
    moved = np.abs(fast.R - state.R).max() + np.abs(fast.t - state.t).max()
    assert moved > 1e-6


def test_compiled_lm_reaches_the_ground_truth_from_a_perturbed_start(paper_scene, rng):
    """LM (compiled) on exact level-6 data, started 1 deg / 3 deg off with zero velocities,
    finds the zero-residual ground truth."""
    from rsvo_ros.twoview.solver import levenberg_marquardt, residuals

    pair = paper_scene.frame_pair(np.random.default_rng(3), level=6)
    row_ref = pair.K[1, 2]
    R_m, t_m, _ = pose_at_row(pair.R, pair.t, pair.w_prev, pair.v_prev, pair.w_curr,
                              pair.v_curr, row_ref, pair.line_delay)
    corr = make_correspondences(pair.pts_prev, pair.pts_curr, pair.K, pair.line_delay, row_ref)
    start = RSBatch.from_pose(R_m @ so3_exp(np.radians([1.0, 0.0, 0.0])),
                              t_m / np.linalg.norm(t_m) + [0.05, 0.0, 0.0])
    assert np.abs(residuals(start, corr)).max() > 1.0
    found, _, iterations = levenberg_marquardt(start, corr, 100, rel_tol=0.0)
    assert iterations > 0
    assert np.abs(residuals(found, corr)).max() < 1e-6


def test_constant_velocity_of_a_screw_motion():
    """A screw along the rotation axis has a constant body twist: the velocities that
    ``constant_velocity`` reads off the relative pose are exactly the twist, in both frames."""
    from rsvo_ros.twoview.search import constant_velocity

    w = np.array([0.3, -0.2, 0.5])  # rad/s, body frame
    v = 4.0 * w / np.linalg.norm(w)  # m/s along the axis: the body velocity stays v
    dt = 1.0 / 30.0
    R_world_curr, p_world_curr = so3_exp(dt * w), dt * v
    R = R_world_curr.T  # X_curr = R X_prev + t
    t = -R_world_curr.T @ p_world_curr
    vel = constant_velocity(RSBatch.from_pose(R, t), dt)[0]
    unit = np.linalg.norm(t)  # velocities are in units of |t| per second
    expected = np.concatenate([w, v / unit, w, v / unit])
    assert np.allclose(vel, expected, rtol=0, atol=TOL["roundtrip"] * np.abs(expected).max())


def test_the_held_out_test_keeps_velocities_only_where_the_data_carry_them():
    """The cross-validated choice between the RS fit and the model without free velocities:
    on strongly distorted data (level 6) the velocities predict held-out points better; on
    global-shutter data an RS fit's velocities only fit the noise and are refused."""
    from rsvo_ros.sim.paper_scene import PaperScene
    from rsvo_ros.twoview.options import LMOptions
    from rsvo_ros.twoview.search import rs_earns_its_velocities
    from rsvo_ros.twoview.solver import SearchLimits, levenberg_marquardt

    lm = LMOptions()
    verdicts = {}
    for name, scene_line_delay in (("rs", 50e-6), ("gs", 0.0)):
        pair = PaperScene(seed=0, line_delay=scene_line_delay).frame_pair(
            np.random.default_rng(3), level=6)
        noise = np.random.default_rng(4).normal(0.0, 0.5, (2,) + pair.pts_prev.shape)
        row_ref = pair.K[1, 2]
        corr = make_correspondences(pair.pts_prev + noise[0], pair.pts_curr + noise[1], pair.K,
                                    50e-6, row_ref)  # the estimator assumes the RS camera
        R_m, t_m, _ = pose_at_row(pair.R, pair.t, pair.w_prev, pair.v_prev, pair.w_curr,
                                  pair.v_curr, row_ref, scene_line_delay)
        null = RSBatch.from_pose(R_m, t_m / np.linalg.norm(t_m))
        limits = SearchLimits(lm.max_angular_velocity, lm.max_readout_translation / corr.s_max)
        rs, _, _ = levenberg_marquardt(null, corr, 50, limits=limits)  # velocities free
        assert np.abs(rs.vel).max() > 0
        verdicts[name] = rs_earns_its_velocities(rs, null, corr, lm, np.random.default_rng(5),
                                                 None, None, limits)
    assert verdicts == {"rs": True, "gs": False}
