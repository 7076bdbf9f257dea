"""SINS / trajectory / IMU-synthesis speed, plus the ins acceptance figures.

    python benchmarks/bench_sins.py [--quick] [--no-accuracy] [--json OUT.json]

Speed (best of --repeat; the machine is shared):
* numba mechanisation (two-sample coning/sculling, gravity with height, Earth + transport rate):
  steps/s of ``sins_run_final`` (state only) and ``sins_run`` (full history), and the per-call cost of
  ``sins_step`` called from Python (the ultra-tight loop's 100 Hz use);
* trajectory queries: us per 1000-point ``pos_vel_e`` (paper-highdyn and a turning vehicle) and per
  1000-point ``kinematics``;
* IMU synthesis of the 60 s paper flight at 100 Hz;
* error model: F build and Van Loan discretisation (15 and 17 states).

Accuracy (unless --no-accuracy): error-free free-inertial errors at 60 s on paper-highdyn at 100 and
200 Hz; 10-min static Schuler check with the paper biases; 60 s linearisation check of the error model.
"""

import argparse
import json
import math
import time

import numpy as np

from _common import add_common_args, best, finish


def speed(quick, repeat):
    from ultratight.ins import error_model as em
    from ultratight.ins.imu import synthesize_imu
    from ultratight.ins.sins import make_state, sins_run, sins_run_final, sins_step
    from ultratight.ins.trajectory import PAPER_HIGHDYN_RECEIVER, PAPER_HIGHDYN_TRAJECTORY, build_trajectory

    res = {}
    n = 200_000 if quick else 2_000_000
    rng = np.random.default_rng(0)
    dt = 0.01
    dth = np.tile(np.array([1e-4, -2e-5, 3e-5]), (n, 1)) + rng.normal(size=(n, 3)) * 1e-7
    dv = np.tile(np.array([0.5, 0.01, 0.098]), (n, 1)) + rng.normal(size=(n, 3)) * 1e-5
    x0 = make_state(np.array([1.0, 0, 0, 0]), np.array([100.0, 10.0, 0.0]),
                    np.array([math.radians(28.2), math.radians(102.0), 5e4]))
    sins_run_final(x0, dth[:10], dv[:10], dt)
    sins_run(x0, dth[:10], dv[:10], dt)
    t = best(lambda: sins_run_final(x0, dth, dv, dt), repeat)
    res["sins_steps_per_s"] = n / t
    t = best(lambda: sins_run(x0, dth, dv, dt), repeat)
    res["sins_run_with_history_steps_per_s"] = n / t
    x = x0.copy()
    m = 20000
    t0 = time.perf_counter()
    for k in range(m):
        sins_step(x, dth[k], dv[k], dt)
    res["sins_step_from_python_us"] = (time.perf_counter() - t0) / m * 1e6

    tr = build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 60.0)
    turns = build_trajectory({"kind": "turns", "speed0_mps": 30.0, "segments": [
        {"t0": 0.0, "turn_rate_dps": 0.0}, {"t0": 10.0, "turn_rate_dps": 37.45},
        {"t0": 30.0, "turn_rate_dps": -37.45}, {"t0": 50.0, "turn_rate_dps": 0.0}]},
        {"lat_deg": 45.0, "lon_deg": 7.0, "h_m": 200.0}, 60.0)
    tq = np.linspace(0.0, 60.0, 1000)
    reps = 200 if quick else 1000
    for name, trj in (("paper", tr), ("turns", turns)):
        trj.pos_vel_e(tq)
        t = best(lambda: [trj.pos_vel_e(tq) for _ in range(reps)], repeat)
        res[f"traj_pos_vel_e_1000pts_us_{name}"] = t / reps * 1e6
    tr.kinematics(tq)
    t = best(lambda: [tr.kinematics(tq) for _ in range(20)], repeat)
    res["traj_kinematics_1000pts_us"] = t / 20 * 1e6
    synthesize_imu(tr, 100.0, duration_s=1.0)
    t = best(lambda: synthesize_imu(tr, 100.0), max(1, repeat // 2))
    res["imu_synthesis_60s_100hz_s"] = t

    q = np.array([1.0, 0, 0, 0])
    v = np.array([100.0, 10.0, 0.0])
    llh = np.array([0.5, 1.7, 5e4])
    f = np.array([1.0, 0.0, 9.8])
    for ns in (em.N15, em.N17):
        em.F_matrix(q, v, llh, f, n_states=ns)
        t = best(lambda: [em.F_matrix(q, v, llh, f, n_states=ns) for _ in range(200)], repeat)
        res[f"F_matrix_{ns}_us"] = t / 200 * 1e6
        F = em.F_matrix(q, v, llh, f, n_states=ns)
        G = em.G_matrix(q, n_states=ns)
        Qc = np.ones(G.shape[1]) * 1e-6
        t = best(lambda: [em.discretize(F, G, Qc, 0.01) for _ in range(100)], repeat)
        res[f"van_loan_{ns}_us"] = t / 100 * 1e6
    return res


def accuracy():
    from scipy.linalg import expm

    from ultratight.ins import error_model as em
    from ultratight.ins.attitude import quat_mult, quat_to_dcm, rotvec_to_quat
    from ultratight.ins.earth import normal_gravity, radii
    from ultratight.ins.imu import apply_errors, imu_errors_from_config, synthesize_imu
    from ultratight.ins.sins import make_state, nav_errors, sins_run
    from ultratight.ins.trajectory import PAPER_HIGHDYN_RECEIVER, PAPER_HIGHDYN_TRAJECTORY, build_trajectory

    res = {}
    tr = build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 60.0)

    def run(imu, dth=None, dv=None, x0=None):
        T = imu.truth
        x0 = make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0]) if x0 is None else x0
        q, v, p = sins_run(x0, imu.dtheta_b if dth is None else dth, imu.dv_b if dv is None else dv,
                           1.0 / imu.rate_hz)
        return (q, v, p), nav_errors(q, v, p, T["q_lb"], T["vel_l"], T["llh"])

    imus = {}
    for rate in (100.0, 200.0):
        imus[rate] = imu = synthesize_imu(tr, rate)
        _, (dp, dv, da) = run(imu)
        res[f"error_free_{int(rate)}hz"] = {
            "pos_err_60s_m": float(np.linalg.norm(dp[-1])), "max_pos_err_m": float(np.linalg.norm(dp, axis=1).max()),
            "vel_err_60s_mps": float(np.linalg.norm(dv[-1])),
            "att_err_60s_deg": float(np.degrees(np.linalg.norm(da[-1])))}

    # error-free turning vehicle (2 g turns at 30 m/s, 37.45 deg/s: coning and sculling), 60 s,
    # largest errors over the run (docs/ins.md "Measured figures")
    turns = build_trajectory({"kind": "turns", "speed0_mps": 30.0, "heading0_deg": 0.0, "segments": [
        {"t0": 0.0, "turn_rate_dps": 0.0}, {"t0": 10.0, "turn_rate_dps": 37.45}, {"t0": 20.0, "turn_rate_dps": 0.0},
        {"t0": 30.0, "turn_rate_dps": -37.45}, {"t0": 40.0, "turn_rate_dps": 0.0, "speed_mps": 20.0}]},
        {"lat_deg": 45.0, "lon_deg": 7.0, "h_m": 200.0}, 60.0)
    for rate in (100.0, 200.0):
        _, (dp, dv, da) = run(synthesize_imu(turns, rate))
        res[f"turns_error_free_{int(rate)}hz"] = {
            "max_pos_err_m": float(np.linalg.norm(dp, axis=1).max()),
            "max_vel_err_mps": float(np.linalg.norm(dv, axis=1).max()),
            "max_att_err_deg": float(np.degrees(np.linalg.norm(da, axis=1).max()))}

    # static Schuler / vertical-channel check (paper biases, no noise, 10 min)
    st = build_trajectory({"kind": "static", "attitude": "fixed"}, PAPER_HIGHDYN_RECEIVER, 600.0)
    imu = synthesize_imu(st, 100.0)
    err = imu_errors_from_config({"preset": "paper"})
    err.gyro_arw[:] = 0.0
    err.accel_vrw[:] = 0.0
    dth, dvv = apply_errors(imu.dtheta_b, imu.dv_b, err, None, 0.01)
    _, (dp, dv, _) = run(imu, dth, dvv)
    T = imu.truth
    lat, h = T["llh"][0, 0], T["llh"][0, 2]
    rm, rn = radii(lat)
    R = math.sqrt(rm * rn) + h
    g = normal_gravity(lat, h)
    ws, k = math.sqrt(g / R), math.sqrt(2 * g / R)
    t = T["t"]
    C = quat_to_dcm(T["q_lb"][0])
    eps, nab = C @ err.gyro_bias, C @ err.accel_bias
    s, c = np.sin(ws * t), np.cos(ws * t)
    v_cf = np.stack([nab[0] * s / ws + R * eps[1] * (1 - c), nab[1] * s / ws - R * eps[0] * (1 - c),
                     nab[2] * np.sinh(k * t) / k], axis=1)
    p_cf = np.stack([nab[0] * (1 - c) / ws ** 2 + R * eps[1] * (t - s / ws),
                     nab[1] * (1 - c) / ws ** 2 - R * eps[0] * (t - s / ws),
                     nab[2] * (np.cosh(k * t) - 1) / k ** 2], axis=1)
    res["static_600s_paper_biases"] = {
        "pos_err_enu_m": dp[-1].tolist(), "closed_form_pos_enu_m": p_cf[-1].tolist(),
        "vel_err_enu_mps": dv[-1].tolist(), "closed_form_vel_enu_mps": v_cf[-1].tolist(),
        "max_rel_dev_vel": [float(np.abs(dv[:, a] - v_cf[:, a]).max() / np.abs(v_cf[:, a]).max()) for a in range(3)],
        "max_rel_dev_pos": [float(np.abs(dp[:, a] - p_cf[:, a]).max() / np.abs(p_cf[:, a]).max()) for a in range(3)],
    }

    # linearisation check (error model vs mechanisation, 60 s paper-highdyn)
    imu = imus[100.0]
    T = imu.truth
    dt = 0.01
    err = imu_errors_from_config({"preset": "paper"})
    err.gyro_arw[:] = 0.0
    err.accel_vrw[:] = 0.0
    dth, dvv = apply_errors(imu.dtheta_b, imu.dv_b, err, None, dt)
    lat0, h0 = T["llh"][0, 0], T["llh"][0, 2]
    rm, rn = radii(lat0)
    phi0 = np.array([2e-4, -1e-4, 3e-4])
    dv0 = np.array([0.05, -0.03, 0.02])
    dp0 = np.array([10.0 / (rm + h0), -8.0 / ((rn + h0) * math.cos(lat0)), 5.0])
    x0 = make_state(quat_mult(rotvec_to_quat(-phi0), T["q_lb"][0]), T["vel_l"][0] + dv0, T["llh"][0] + dp0)
    (q, v, p), _ = run(imu, dth, dvv, x0)
    idx = np.arange(0, imu.n + 1, 10)
    actual = np.array([em.true_error_state(q[i], v[i], p[i], T["q_lb"][i], T["vel_l"][i], T["llh"][i]) for i in idx])
    dx = np.concatenate([phi0, dv0, dp0, err.gyro_bias, err.accel_bias])
    model = [dx[:9].copy()]
    for j in range(len(idx) - 1):
        kk = idx[j] + 5
        F = em.F_matrix(T["q_lb"][kk], T["vel_l"][kk], T["llh"][kk], imu.dv_b[kk] / dt)
        dx = expm(F * 0.1) @ dx
        model.append(dx[:9].copy())
    model = np.array(model)
    scale = np.array([1, 1, 1, 1, 1, 1, rm + h0, (rn + h0) * math.cos(lat0), 1.0])
    lin = {}
    for name, sl in (("att", em.ATT), ("vel", em.VEL), ("pos", em.POS)):
        a, m = actual[:, sl] * scale[sl], model[:, sl] * scale[sl]
        lin[f"{name}_max_rel_dev"] = float(np.abs(a - m).max() / np.abs(a).max())
        lin[f"{name}_final_actual"] = a[-1].tolist()
        lin[f"{name}_final_model"] = m[-1].tolist()
    res["linearisation_60s_paper_highdyn"] = lin
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    out = {"speed": speed(args.quick, args.repeat)}
    if not (args.no_accuracy or args.quick):
        out["accuracy"] = accuracy()
    for k, v in out["speed"].items():
        print(f"{k:40s} {v:12.4g}" if isinstance(v, (int, float)) else f"{k:40s} {v}")
    if "accuracy" in out:
        print(json.dumps(out["accuracy"], indent=2))
    finish(args, out)

if __name__ == "__main__":
    main()
