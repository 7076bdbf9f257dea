"""Loose/tight SINS/GNSS runners (fusion.integration) on the Fang 2017 / Cai et al. 2020 experiments' data:
closed-loop runs against simulator truth, covariance consistency (NEES), the χ² + Newton
cores' false alarms and gross-error rejection, the adaptive cores with the paper's wrong noise."""

import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.coupling import integration as I
from ultratight.ins import error_model as em
from ultratight.ins.sins import sins_run_final
from ultratight.receiver.cli import experiments as E
from ultratight.fusion.experiments import paper_robust_flight as RF
from ultratight.fusion.experiments import paper_static_iakf as SI
@pytest.fixture(scope="module")
def flight():
    path, raw, _ = E.resolve("paper-robust-flight")
    cfg = RF.load(path, raw, {})
    return cfg, [RF.simulate(cfg, s) for s in (1, 2)]


@pytest.fixture(scope="module")
def static(shared_data):
    path, raw, _ = E.resolve("paper-static-iakf")
    cfg = SI.load(path, raw, {"duration_s": 400.0})
    return cfg, SI.simulate(cfg, 1)


IAKF_POS_RMS_3D_M = float(np.linalg.norm([1.00, 0.63, 1.36]))   # README: IAKF lat / lon / h RMS, 1000 s


def _rms(res, block, t_from=0.0):
    sel = res["t"] >= t_from
    return np.sqrt(np.mean(res["err"][sel][:, block] ** 2, axis=0))


def _in_band(res, n):
    lo, hi = I.nees_band(n)
    return float(np.mean((res["nees"] >= lo) & (res["nees"] <= hi)))


def test_ins_only_is_the_free_inertial_solution(flight):
    """No update: the runner's chunked mechanisation equals one run over all IMU samples."""
    cfg, runs = flight
    inp, data = runs[0]
    res = RF.run_method(cfg, "ins-only", inp, RF.fixes(cfg, data, None))
    dt = inp.t_imu[1] - inp.t_imu[0]
    x = sins_run_final(inp.x0_est, inp.dtheta, inp.dv, dt)
    e_pos = (x[7:10] - inp.truth_llh[-1]) * I.pos_scale(inp.truth_llh[-1, 0], inp.truth_llh[-1, 2])
    np.testing.assert_allclose(res["err"][-1, em.POS], e_pos, rtol=1e-9, atol=1e-6)
    # with 0.01 g accelerometer biases the free inertial error is kilometres after 500 s
    assert np.linalg.norm(res["err"][-1, em.POS]) > 500.0


def test_kf_on_clean_data_is_accurate_and_consistent(flight):
    """Loose KF, no gross errors: errors at the level the GNSS σ allows, and the full 15-state NEES
    inside the 95 % χ² band for ≥ 90 % of epochs (consistency acceptance)."""
    cfg, runs = flight
    for inp, data in runs:
        res = RF.run_method(cfg, "kf", inp, RF.fixes(cfg, data, None))
        assert np.all(_rms(res, em.POS) < 5.0), _rms(res, em.POS)       # GNSS σ 16.7 / 13.8 / 5 m
        assert np.all(_rms(res, em.VEL) < 0.25), _rms(res, em.VEL)      # GNSS σ 0.28 m/s
        assert _in_band(res, 15) >= 0.90


def test_nees_check_catches_an_optimistic_covariance(flight):
    """The same run with R 100x too small (a badly optimistic core): the NEES test fails."""
    cfg, runs = flight
    inp, data = runs[0]
    fx = RF.fixes(cfg, data, None)
    q, R, P0 = RF.noise_model(cfg, inp.truth_llh[0])
    res = I.run_integration("loose", I.make_core("kf", P0, None, R), inp,
                            I.loose_measurement_fn(fx[0], fx[1], fx[2], R / 100.0), q)
    assert _in_band(res, 15) < 0.5


def test_chi2_newton_false_alarms_and_cost_on_clean_data(flight):
    """Per-dimension false-alarm rate on clean data within a factor 2 of α = 0.01; both readings'
    cost on clean data is bounded (a false alarm swaps one noise sample for a Newton
    extrapolation of std ≈ 2.1σ): < 15 % position RMS per seed against the KF (measured 1–9 %;
    the 10-seed means are in docs/integration-experiments.md)."""
    cfg, runs = flight
    fa = {}
    ratio = []
    for inp, data in runs:
        fx = RF.fixes(cfg, data, None)
        kf = RF.run_method(cfg, "kf", inp, fx)
        for m in ("chi2-newton", "chi2-newton-lit"):
            r = RF.run_method(cfg, m, inp, fx)
            fa.setdefault(m, []).append(r["n_faults"] / r["n_screened"])
            ratio.append(np.linalg.norm(_rms(r, em.POS)) / np.linalg.norm(_rms(kf, em.POS)))
    for m, v in fa.items():
        assert 0.005 <= np.mean(v) <= 0.02, (m, v)
    assert max(ratio) < 1.15, ratio


def test_chi2_newton_rejects_gross_errors(flight):
    """Gross errors ×20 every 10 s: both readings cut the KF's position and velocity RMS by ≥ 70 %
    (measured 73–84 % per seed, docs); at ×50 by ≥ 75 % (measured 81–92 %)."""
    cfg, runs = flight
    for inp, data in runs:
        for factor, need in ((20.0, 0.70), (50.0, 0.75)):
            fx = RF.fixes(cfg, data, factor)
            kf = RF.run_method(cfg, "kf", inp, fx)
            for m in ("chi2-newton", "chi2-newton-lit"):
                r = RF.run_method(cfg, m, inp, fx)
                for block in (em.POS, em.VEL):
                    red = 1.0 - np.linalg.norm(_rms(r, block)) / np.linalg.norm(_rms(kf, block))
                    assert red >= need, (factor, m, block, red)


def test_newton_replacement_guard_prevents_runaway(flight):
    """Without the guard and the persistent-fault release, the implementable reading's replaced
    innovations feed the unstable Newton recursion (roots of modulus 1.07) — with them, the run
    stays at the clean-data error level (seed 2, gross errors ×20)."""
    cfg, runs = flight
    inp, data = runs[1]
    fx = RF.fixes(cfg, data, 20.0)
    q, R, P0 = RF.noise_model(cfg, inp.truth_llh[0])
    out = {}
    for guard, release in ((False, None), (True, 3)):
        core = I.make_core("chi2-newton", P0, None, R, newton_guard=guard, release_after=release)
        res = I.run_integration("loose", core, inp, I.loose_measurement_fn(*fx, R), q)
        out[guard] = np.linalg.norm(_rms(res, em.POS))
    assert out[True] < 10.0 < out[False], out


def test_tight_akf0_consistent_and_akf_with_wrong_noise_worse(static):
    """Fang 2017 static case: AKF0 (true noise) with velocity RMS of a few cm/s and its 17-state NEES
    in the 95 % band ≥ 90 % of epochs; AKF started from the paper's wrong settings ≥ 5x worse in
    velocity; IAKF (same wrong settings, the scenario's defaults) near AKF0 after the start-up and
    ≥ 5x better than AKF in horizontal velocity."""
    cfg, (inp, obs) = static
    akf0 = SI.run_method(cfg, "akf0", inp, obs)
    akf = SI.run_method(cfg, "akf", inp, obs)
    iakf = SI.run_method(cfg, "iakf", inp, obs)
    v0 = _rms(akf0, em.VEL, t_from=100.0)          # after the start-up transient
    assert np.all(v0 < 0.1), v0
    assert _in_band(akf0, 17) >= 0.90
    assert np.all(_rms(akf, em.VEL, t_from=100.0) > 5.0 * v0), (_rms(akf, em.VEL, t_from=100.0), v0)
    # README / docs/integration-experiments.md "paper-static-iakf": IAKF position RMS lat/lon/h
    # 1.00 / 0.63 / 1.36 m (1000 s, mean of 10 seeds; 3-D 1.80 m).  This fixture is 400 s, where the
    # start-up transient weighs 2.5x more: seed 1 1.29 / 1.07 / 1.20 m (3-D 2.05 m; 1000 s: 0.73 /
    # 0.60 / 0.93 m); seeds 1-5 at 400 s 3-D 1.96-2.98 m.  Bound = 2 x the documented 3-D figure
    assert np.all(np.isfinite(iakf["err"]))
    assert np.linalg.norm(_rms(iakf, em.POS)) < 2.0 * IAKF_POS_RMS_3D_M, _rms(iakf, em.POS)
    vi = _rms(iakf, em.VEL, t_from=100.0)
    assert np.linalg.norm(vi) < 1.5 * np.linalg.norm(v0), (vi, v0)
    assert np.all(_rms(akf, em.VEL, t_from=100.0)[:2] > 5.0 * vi[:2]), (_rms(akf, em.VEL, t_from=100.0), vi)


def test_iakf_growing_start_and_q_ceiling_help(static):
    """The two IAKF choices of docs/integration-experiments.md, each against the run without it on
    the same data: estimating R̂, Q̂ from the first epoch ("growing") instead of after a full window
    of the wrong settings, and capping the projected Q̂ at the given noise, both lower the
    whole-run velocity RMS.  The diagnostic bound kf-true-noise (true Q, R, the wrong P0) shows
    what the wrong initial covariance alone costs in vertical velocity."""
    cfg, (inp, obs) = static
    f = cfg["filter"]
    base = np.linalg.norm(_rms(SI.run_method(cfg, "iakf", inp, obs), em.VEL))
    fw = SI.run_method({**cfg, "filter": {**f, "iakf_start": "full-window"}}, "iakf", inp, obs)
    noceil = SI.run_method({**cfg, "filter": {**f, "iakf_q_ceiling": False}}, "iakf", inp, obs)
    assert base < 0.6 * np.linalg.norm(_rms(fw, em.VEL)), (base, _rms(fw, em.VEL))
    assert base < 0.9 * np.linalg.norm(_rms(noceil, em.VEL)), (base, _rms(noceil, em.VEL))
    akf0 = SI.run_method(cfg, "akf0", inp, obs)
    bound = SI.run_method(cfg, "kf-true-noise", inp, obs)
    assert _rms(bound, em.VEL)[2] > 2.0 * _rms(akf0, em.VEL)[2]


def test_discrete_model_basis_spans_its_q(static):
    """The eq. 3 noise basis of the discrete model: Q_d = Q_fixed + Σ q_i B_i at the model's own
    PSDs (gyro 3, accelerometer 3, clock bias and drift), and the IAKF core with the model-structured
    Q̂ keeps Q inside that span."""
    cfg, (inp, obs) = static
    q, _, _, _ = SI.noise_settings(cfg, True)
    q[em.NOISE_CLK], q[em.NOISE_DRIFT] = 0.5, 0.2
    x = inp.x0_est
    Phi, Qd, B, Qf = I.discrete_model(x, np.array([0.0, 0.0, 9.8]), 1.0, q, em.N17, basis=True)
    assert B.shape == (8, em.N17, em.N17)
    w = np.concatenate([q[em.NOISE_GYRO], q[em.NOISE_ACCEL], [q[em.NOISE_CLK], q[em.NOISE_DRIFT]]])
    Phi2, Qd2 = I.discrete_model(x, np.array([0.0, 0.0, 9.8]), 1.0, q, em.N17)
    np.testing.assert_allclose(Phi, Phi2)
    Qc = Qf + np.tensordot(w, B, axes=1)
    np.testing.assert_allclose(Qc[:15, :15], Qd2[:15, :15], rtol=1e-9, atol=1e-9 * np.abs(Qd2[:15, :15]).max())
    np.testing.assert_allclose(Qc[em.CLK:, em.CLK:], [[q[em.NOISE_CLK] + q[em.NOISE_DRIFT] / 3, q[em.NOISE_DRIFT] / 2],
                                                      [q[em.NOISE_DRIFT] / 2, q[em.NOISE_DRIFT]]])
    cfg2 = {**cfg, "filter": {**cfg["filter"], "iakf_q_structure": "model"}}
    core_res = SI.run_method(cfg2, "iakf", inp, obs)
    # docs/integration-experiments.md variants table, `iakf_q_structure = "model"`: 1.00 / 0.63 / 1.37 m
    # (1000 s, 10 seeds); 400 s seed 1: 1.28 / 1.07 / 1.19 m, seeds 1-5 within 0.02 m of the default
    # core; bound as above, 2 x the documented 3-D figure
    assert np.all(np.isfinite(core_res["err"]))
    assert np.linalg.norm(_rms(core_res, em.POS)) < 2.0 * np.linalg.norm([1.00, 0.63, 1.37]), _rms(core_res, em.POS)


def test_kf_range_distance_is_zero_on_the_papers_extents():
    assert RF.kf_range_distance([1000.0, 2000.0, 200.0], [2.0, 5.0, 2.0]) == (0.0, 0.0, 0.0)
    d = RF.kf_range_distance([100.0, 200.0, 20.0], [2.0, 5.0, 2.0])
    assert d[1] == pytest.approx(math.log(10.0)) and d[2] == 0.0 and d[0] == pytest.approx(math.log(10.0) / 2)


def test_make_core_names():
    P0 = np.eye(15)
    for name in ("kf", "ins-only", "chi2-newton", "chi2-newton-lit"):
        assert I.make_core(name, P0, None, np.eye(6)) is not None
    with pytest.raises(ConfigError, match="unknown integration core 'ekf2'"):
        I.make_core("ekf2", P0, None, np.eye(6))
    lo, hi = I.nees_band(15)
    assert lo == pytest.approx(6.262, abs=1e-3) and hi == pytest.approx(27.488, abs=1e-3)
    assert math.isclose(I.pos_scale(0.0, 0.0)[2], 1.0)
