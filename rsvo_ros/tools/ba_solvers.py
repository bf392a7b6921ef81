"""The window BA solved three ways on the same windows: time per window and final cost.

    python -m rsvo_ros.tools.ba_solvers [--frames 150] [--severity 1.0] [--windows 12]

Windows are taken from a synthetic hand-held walk (``rsvo_synth --motion walk``) as the window
backend meets them (the problem just before each keyframe's BA), with the keyframes' angular
accelerations held at zero (the 12 parameters per frame the comparison was made with). Solvers:

- ``compiled``: the package's Levenberg-Marquardt with a Schur complement on the inverse depths
  (numba, :func:`rsvo_ros.odometry.local_map.solve_window`);
- ``scipy``: ``scipy.optimize.least_squares`` (trust region reflective, LSMR on the sparse
  analytic Jacobian, Cauchy loss);
- ``gtsam``: GTSAM's Levenberg-Marquardt over custom factors (Pose3, Vector3 velocities,
  Vector1 inverse depths; the residual and Jacobians from the same kernels, called from
  Python), where ``gtsam`` imports (it is not a dependency of the package).

Every solution is scored with the same robust cost. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time

import numpy as np

from rsvo_ros.core.geometry import so3_exp, so3_right_jacobian
from rsvo_ros.odometry import rs_projection as rp
from rsvo_ros.odometry.local_map import LocalMap, WindowProblem, solve_window

ITERATIONS = 10
NO_ACC = (0.0, 0.0, 0.0)  # the windows' angular accelerations are held at zero


def collect_windows(frames: int, severity: float, count: int, seed: int = 0
                    ) -> list[WindowProblem]:  # fmt: skip
    """Window problems of a synthetic walk, as the backend builds them before each BA."""
    from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
    from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig

    cfg = SynthConfig(frames=frames, motion="walk", severity=severity, seed=seed)
    renderer = SequenceRenderer(cfg)
    options = PipelineOptions(backend="window")
    options.window.map.prior_acc_rad_s2 = 0.0  # accelerations held: 12 parameters per frame
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, options)
    found: list[WindowProblem] = []
    original = LocalMap.optimize

    def capture(self, iterations=None):
        prob = self.problem()
        if prob is not None and len(prob.R) >= 3:
            found.append(copy.deepcopy(prob))
        return original(self, iterations)

    LocalMap.optimize = capture
    try:
        for f in renderer:
            pipe.process(round(f.stamp * 1e9), f.image)
    finally:
        LocalMap.optimize = original
    step = max(1, len(found) // count)
    return found[::step][:count]


def cost_of(prob: WindowProblem, R, p, w, v, rho) -> float:
    res = np.zeros((len(prob.obs_kf), 2))
    return float(rp._window_cost(R, p, w, v, prob.acc, prob.obs_kf, prob.obs_lm, prob.obs_x,
                                 prob.obs_s, prob.lm_anchor, prob.lm_x, prob.lm_s, rho,
                                 prob.focal, prob.robust_px, prob.prior_mu, prob.prior_p2,
                                 prob.acc_p2, res))  # fmt: skip


# --------------------------------------------------------------------------- scipy


def _jacobian_rows(prob: WindowProblem, R, p, w, v, rho):
    """Residuals (2n,) and their Jacobian blocks per observation: frame (2, 15), anchor
    (2, 15), rho (2,) (the accelerations held at zero)."""
    n = len(prob.obs_kf)
    e = np.zeros((n, 2))
    Jf = np.zeros((n, 2, rp.FRAME_PARAMS))
    Ja = np.zeros((n, 2, rp.FRAME_PARAMS))
    Jr = np.zeros((n, 2))
    JA, Jrho = np.empty((3, rp.FRAME_PARAMS)), np.empty(3)
    jf, jx = np.empty((2, rp.FRAME_PARAMS)), np.empty((2, 3))
    for o in range(n):
        k, j = prob.obs_kf[o], prob.obs_lm[o]
        a = prob.lm_anchor[j]
        X = rp._landmark(rp._rows(R[a]), tuple(p[a]), tuple(w[a]), tuple(v[a]), NO_ACC,
                         prob.lm_s[j], tuple(prob.lm_x[j]), rho[j], JA, Jrho)  # fmt: skip
        ex, ey, ok = rp._observe(rp._rows(R[k]), tuple(p[k]), tuple(w[k]), tuple(v[k]), NO_ACC,
                                 prob.obs_s[o], X, tuple(prob.obs_x[o]), prob.focal, jf, jx)
        if not ok:
            continue
        e[o] = ex, ey
        Jf[o] = jf
        Ja[o] = jx @ JA
        Jr[o] = jx @ Jrho
    return e, Jf, Ja, Jr


def solve_scipy(prob: WindowProblem, iterations: int = ITERATIONS):
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    K, M, n = len(prob.R), len(prob.rho), len(prob.obs_kf)
    free = prob.col >= 0
    n_x = prob.n_cols + M
    prior_sd = np.sqrt(prob.prior_p2)

    def unpack(x):
        d = np.zeros((K, rp.FRAME_PARAMS))
        d[free] = x[prob.col[free]]
        R = np.stack([prob.R[k] @ so3_exp(d[k, 0:3]) for k in range(K)])
        return R, prob.p + d[:, 3:6], prob.w + d[:, 6:9], prob.v + d[:, 9:12], \
            np.clip(x[prob.n_cols:], rp.RHO_MIN, rp.RHO_MAX), d

    def fun(x):
        R, p, w, v, rho, _ = unpack(x)
        e, *_ = _jacobian_rows(prob, R, p, w, v, rho)
        pri = (np.concatenate([w, v], axis=1) - prob.prior_mu) * prior_sd
        return np.concatenate([e.ravel(), pri.ravel()])

    def jac(x):
        R, p, w, v, rho, d = unpack(x)
        _, Jf, Ja, Jr = _jacobian_rows(prob, R, p, w, v, rho)
        jr_rot = [so3_right_jacobian(d[k, 0:3]) for k in range(K)]  # R0 Exp(d) chart
        rows, cols, vals = [], [], []
        for o in range(n):
            for J, f in ((Jf[o], prob.obs_kf[o]), (Ja[o], prob.lm_anchor[prob.obs_lm[o]])):
                J = J.copy()
                J[:, 0:3] = J[:, 0:3] @ jr_rot[f]
                for i in range(rp.FRAME_PARAMS):
                    c = prob.col[f, i]
                    if c >= 0:
                        rows += [2 * o, 2 * o + 1]
                        cols += [c, c]
                        vals += [J[0, i], J[1, i]]
            c = prob.n_cols + prob.obs_lm[o]
            rows += [2 * o, 2 * o + 1]
            cols += [c, c]
            vals += [Jr[o, 0], Jr[o, 1]]
        for k in range(K):
            for i in range(6):
                c = prob.col[k, 6 + i]
                if c >= 0:
                    rows.append(2 * n + 6 * k + i)
                    cols.append(c)
                    vals.append(prior_sd[k, i])
        return coo_matrix((vals, (rows, cols)), shape=(2 * n + 6 * K, n_x)).tocsr()

    x0 = np.concatenate([np.zeros(prob.n_cols), prob.rho])
    out = least_squares(fun, x0, jac=jac, loss="cauchy", f_scale=prob.robust_px,
                        method="trf", tr_solver="lsmr", x_scale="jac",
                        max_nfev=iterations + 1)  # fmt: skip
    R, p, w, v, rho, _ = unpack(out.x)
    return R, p, w, v, rho, int(out.nfev)


# --------------------------------------------------------------------------- GTSAM


def solve_gtsam(prob: WindowProblem, iterations: int = ITERATIONS):
    import gtsam

    K = len(prob.R)
    X = lambda k: gtsam.symbol("x", k)  # noqa: E731
    W = lambda k: gtsam.symbol("w", k)  # noqa: E731
    V = lambda k: gtsam.symbol("v", k)  # noqa: E731
    L = lambda j: gtsam.symbol("l", j)  # noqa: E731
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(K):
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(prob.R[k]), prob.p[k]))
        values.insert(W(k), prob.w[k])
        values.insert(V(k), prob.v[k])
        if prob.col[k, 0] < 0:  # a held pose
            graph.add(gtsam.NonlinearEqualityPose3(X(k), values.atPose3(X(k))))
        for key, mu, sd in ((W(k), prob.prior_mu[k, :3], prob.prior_p2[k, :3]),
                            (V(k), prob.prior_mu[k, 3:], prob.prior_p2[k, 3:])):
            if np.all(sd > 0):
                graph.add(gtsam.PriorFactorVector(key, mu, gtsam.noiseModel.Diagonal.Sigmas(
                    1.0 / np.sqrt(sd))))
    for j in range(len(prob.rho)):
        values.insert(L(j), np.array([prob.rho[j]]))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(
        prob.robust_px), gtsam.noiseModel.Isotropic.Sigma(2, 1.0))

    def factor(o: int):
        k, j = int(prob.obs_kf[o]), int(prob.obs_lm[o])
        a = int(prob.lm_anchor[j])
        JA, Jrho = np.empty((3, rp.FRAME_PARAMS)), np.empty(3)
        jf, jx = np.empty((2, rp.FRAME_PARAMS)), np.empty((2, 3))

        def error(this, vals, H):
            Tk, Ta = vals.atPose3(X(k)), vals.atPose3(X(a))
            Rk, Ra = Tk.rotation().matrix(), Ta.rotation().matrix()
            pk, pa = Tk.translation(), Ta.translation()
            wk, vk = vals.atVector(W(k)), vals.atVector(V(k))
            wa, va = vals.atVector(W(a)), vals.atVector(V(a))
            rho = float(vals.atVector(L(j))[0])
            Xw = rp._landmark(rp._rows(Ra), tuple(pa), tuple(wa), tuple(va), NO_ACC,
                              prob.lm_s[j], tuple(prob.lm_x[j]), rho, JA, Jrho)  # fmt: skip
            ex, ey, _ = rp._observe(rp._rows(Rk), tuple(pk), tuple(wk), tuple(vk), NO_ACC,
                                    prob.obs_s[o], Xw, tuple(prob.obs_x[o]), prob.focal, jf, jx)
            if H is not None:
                Jan = jx @ JA
                # GTSAM's Pose3 tangent: [body rotation, body translation]
                H[0] = np.hstack([jf[:, 0:3], jf[:, 3:6] @ Rk])
                H[1] = jf[:, 6:9].copy()
                H[2] = jf[:, 9:12].copy()
                H[3] = np.hstack([Jan[:, 0:3], Jan[:, 3:6] @ Ra])
                H[4] = Jan[:, 6:9].copy()
                H[5] = Jan[:, 9:12].copy()
                H[6] = (jx @ Jrho).reshape(2, 1)
            return np.array([ex, ey])

        keys = [X(k), W(k), V(k), X(a), W(a), V(a), L(j)]
        return gtsam.CustomFactor(noise, keys, error)

    for o in range(len(prob.obs_kf)):
        graph.add(factor(o))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    R = np.stack([result.atPose3(X(k)).rotation().matrix() for k in range(K)])
    p = np.stack([result.atPose3(X(k)).translation() for k in range(K)])
    w = np.stack([result.atVector(W(k)) for k in range(K)])
    v = np.stack([result.atVector(V(k)) for k in range(K)])
    rho = np.array([result.atVector(L(j))[0] for j in range(len(prob.rho))])
    return R, p, w, v, rho, iterations


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.ba_solvers",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--severity", type=float, default=1.0)
    ap.add_argument("--windows", type=int, default=12)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    problems = collect_windows(args.frames, args.severity, args.windows)
    if not problems:
        print("no window of 3 or more keyframes in this walk: give more --frames",
              file=sys.stderr)
        return 1
    solve_window(problems[0], 1)  # the kernels are compiled before anything is timed
    solvers = {"compiled (numba LM + Schur)": lambda pr: _compiled(pr),
               "scipy least_squares (TRF, sparse LSMR)": solve_scipy}
    try:
        import gtsam  # noqa: F401

        solvers["GTSAM LM (custom factors in Python)"] = solve_gtsam
    except ImportError:
        print("gtsam not installed: its column is left out (pip install gtsam)")
    rows = {name: {"ms": [], "cost": []} for name in solvers}
    for prob in problems:
        start = cost_of(prob, prob.R, prob.p, prob.w, prob.v, prob.rho)
        for name, solve in solvers.items():
            t0 = time.perf_counter()
            R, p, w, v, rho, _ = solve(prob)
            rows[name]["ms"].append((time.perf_counter() - t0) * 1e3)
            rows[name]["cost"].append(cost_of(prob, R, p, w, v, rho) / max(start, 1e-12))
    sizes = [(len(p.R), len(p.rho), len(p.obs_kf)) for p in problems]
    print(f"{len(problems)} windows: keyframes {min(s[0] for s in sizes)}-"
          f"{max(s[0] for s in sizes)}, landmarks {min(s[1] for s in sizes)}-"
          f"{max(s[1] for s in sizes)}, observations {min(s[2] for s in sizes)}-"
          f"{max(s[2] for s in sizes)}; {ITERATIONS} iterations each")
    print("| solver | time per window, median (ms) | final cost / start cost, median |")
    print("|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {np.median(r['ms']):.1f} | {np.median(r['cost']):.4f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"sizes": sizes, "rows": rows}, f, indent=1)
    return 0


def _compiled(prob: WindowProblem):
    sol = solve_window(prob, ITERATIONS)
    return sol.R, sol.p, sol.w, sol.v, sol.rho, sol.iterations


if __name__ == "__main__":
    sys.exit(main())
