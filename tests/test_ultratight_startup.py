"""`process --mode ultratight` on a recording as a user has it: IF file + sidecar (no generator
block, no PRN list), a RINEX navigation file and an IMU CSV without truth, in a directory without
any truth file. The engine starts from the scalar receiver's own fix on the same file
(ultratight.receiver.deep.handover) and its outputs are compared with the generator's truth afterwards.

The recording: paper-highdyn (10 g from t = 0, no still interval: the attitude comes from the
specific force and the velocity direction) without its noise burst, 45 dB-Hz: the scalar
receiver must fix under 10 g before the hand-over (at 30 dB-Hz it needs --dynamics high:
tests/test_high_dynamics.py, docs/process.md "High dynamics").
Data bits the receiver cannot know: the generator puts random bits in subframes 4-5 and the reserved
fields (``[nav] data = "lnav-random-sf45"``), so the engine runs with ``--bits blind``.
"""

import json
import math
import re
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from ultratight.receiver.cli import main

FS_HZ = 2.046e6
DURATION_S = 20.0
CN0_DBHZ = 45.0
NAV_DATA = "lnav-random-sf45"        # subframes 4-5 and reserved bits unknowable from the ephemeris
BITS_FLAGS = ["--bits", "blind"]
EXPECTED_BITS = {"blind"}


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], capture_output=True, text=True,
                          cwd=cwd)


def _one_line_error(r):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    from ultratight.ins.imu_data import read_imu_h5, write_imu_csv
    from ultratight.receiver.io.rinex_out import write_rinex_nav
    from ultratight.config import locate_scenario
    from ultratight.signals.constellation import nominal_ephemerides

    d = tmp_path_factory.mktemp("user_rec")
    txt = locate_scenario("paper-highdyn").read_text()
    txt, n = re.subn(r"\[\[noise_events\]\][^\[]*", "", txt)
    assert n == 1
    txt, n = re.subn(r"\[nav\]\n", f'[nav]\ndata = "{NAV_DATA}"\n', txt)
    assert n == 1
    (d / "hd.toml").write_text(txt)
    gen = d / "gen"
    gen.mkdir()
    assert main(["generate", str(d / "hd.toml"), "--duration", str(DURATION_S), "--fs", str(FS_HZ), "--cn0",
                 str(CN0_DBHZ), "--out", str(gen / "ph"), "--no-progress"]) == 0
    user = d / "user"
    user.mkdir()
    side = json.loads((gen / "ph.ci16.json").read_text())
    keep = ("format", "fs_hz", "if_hz", "is_complex", "iq_conj", "start_week", "start_tow_s", "bits")
    (user / "rec.ci16.json").write_text(json.dumps({k: side[k] for k in keep if k in side}))
    shutil.copy(gen / "ph.ci16", user / "rec.ci16")
    imu = read_imu_h5(gen / "ph.imu.h5")
    imu.truth = None
    write_imu_csv(user / "imu.csv", imu)
    write_rinex_nav(user / "nav.rnx", list(nominal_ephemerides(side["start_week"], side["start_tow_s"]).values()))
    assert sorted(p.name for p in user.iterdir()) == ["imu.csv", "nav.rnx", "rec.ci16", "rec.ci16.json"]
    out = d / "out"
    out.mkdir()
    r = _cli("process", "rec.ci16", "--mode", "ultratight", "--imu", "imu.csv", "--ephemeris", "nav.rnx", "--json",
             "--out", str(out / "res.h5"), "--csv", str(out / "nav.csv"), "--kml", str(out / "nav.kml"),
             "--nmea", str(out / "nav.nmea"), "--rinex-obs", str(out / "ut.obs"), *BITS_FLAGS, cwd=user)
    assert r.returncode == 0, r.stderr
    return {"dir": d, "gen": gen, "user": user, "out": out, "summary": json.loads(r.stdout), "sidecar": side}


def _truth_at(traj, t, key):
    tt = traj["t"][()]
    return np.stack([np.interp(t, tt, traj[key][:, i]) for i in range(traj[key].shape[1])], axis=1)


def test_starts_from_own_scalar_fix_and_keeps_every_channel(rec):
    s = rec["summary"]
    assert s["startup"] == "scalar-fix" and s["handover"]["source"] == "scalar-fix"
    assert s["assisted"] == []                       # a user's files: nothing from the generator
    ho = s["handover"]
    # LNAV time of week needs a subframe (6 s) after bit sync: the hand-over comes after it
    assert 6.0 < ho["handover_t_s"] < 12.0
    # no still interval at 10 g: specific force, velocity direction and the coordinated-flight bank
    assert ho["attitude_method"] == "specific-force+velocity-heading+coordinated-bank"
    assert sorted(s["prns"]) == sorted(rec["sidecar"]["prn"])              # every satellite in view, no list given
    assert s["lock_lost_channels"] == []
    assert set(s["bits"]) == {str(p) for p in s["prns"]} and set(s["bits"].values()) == EXPECTED_BITS
    assert s["duration_s"] == pytest.approx(DURATION_S - ho["handover_t_s"], abs=5e-3)


def test_handover_state_within_its_stated_sigmas(rec):
    from ultratight.ins.attitude import quat_to_dcm
    ho = rec["summary"]["handover"]
    with h5py.File(rec["out"] / "res.h5") as f, h5py.File(rec["gen"] / "ph.traj.h5") as g:
        t0 = f["sins/t_s"][0]
        assert t0 == pytest.approx(ho["handover_t_s"], abs=1e-9)
        llh = f["sins/llh"][0]
        vel = f["sins/vel_l"][0]
        q = f["sins/q_lb"][0]
        clk = f["sins/clk"][0]
        sp, sv, sa, sc = (f[f"sins/{k}"][0] for k in ("sigma_pos_l_m", "sigma_vel_l_mps", "sigma_att_rad",
                                                       "sigma_clk"))
        k = int(np.argmin(np.abs(g["t"][()] - t0)))
        assert abs(g["t"][k] - t0) < 1e-9
        lat, lon, h = g["llh"][k]
        from ultratight.ins.earth import radii
        rm, rn = radii(lat)
        d_enu = np.array([(llh[1] - lon) * (rn + h) * math.cos(lat), (llh[0] - lat) * (rm + h), llh[2] - h])
        assert np.all(np.abs(d_enu) < 3.0 * sp), (d_enu, sp)
        assert np.all(np.abs(vel - g["vel_l"][k]) < 3.0 * sv), (vel - g["vel_l"][k], sv)
        # attitude error angles (local frame): C_est = (I - [phi x]) C_true
        E = quat_to_dcm(q) @ quat_to_dcm(g["q_lb"][k]).T
        phi = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]]) * -0.5
        assert np.all(np.abs(phi) < 3.0 * sa), (np.degrees(phi), np.degrees(sa))
        assert np.degrees(np.max(np.abs(phi))) < 1.0       # velocity-aligned body: tilt + heading to < 1 deg
    cfg = rec["sidecar"]["generator"]["receiver"]
    assert abs(clk[0] - cfg["clock_bias_m"]) < 3.0 * sc[0]
    assert abs(clk[1] - cfg["clock_drift_mps"]) < 3.0 * sc[1]


def test_navigation_solution_against_truth(rec):
    """The issue's acceptance figures: 2 m / 0.1 m/s RMS after the hand-over, no channel lost."""
    with h5py.File(rec["out"] / "res.h5") as f, h5py.File(rec["gen"] / "ph.traj.h5") as g:
        t = f["sins/t_s"][()]
        assert np.allclose(np.diff(t), 0.01, atol=1e-9)            # SINS rate: the 100 Hz IMU
        from ultratight.ins.earth import llh_to_ecef_batch
        pos = llh_to_ecef_batch(f["sins/llh"][()])
        vel = f["sins/vel_l"][()]
        e_pos = np.linalg.norm(pos - _truth_at(g, t, "pos_e"), axis=1)
        e_vel = np.linalg.norm(vel - _truth_at(g, t, "vel_l"), axis=1)
    rms_p, rms_v = float(np.sqrt(np.mean(e_pos ** 2))), float(np.sqrt(np.mean(e_vel ** 2)))
    # docs/ultratight.md "Start-up without truth", measured table, row "no noise burst, 20 s":
    # velocity 0.014 m/s RMS; this run (seed 1) 0.0096 m/s; seeds 1-3 0.0096-0.0183 m/s; bound =
    # documented x 1.5 (a doubling breaks it)
    assert rms_v <= 1.5 * 0.014, rms_v
    # same row: position 1.85 m RMS; this run 1.49 m; seeds 1.11-1.49 m; bound = the 2 m
    # acceptance figure (documented x 1.08)
    assert rms_p <= 2.0, rms_p


def test_no_channel_lost_against_truth(rec):
    """The scenario's loss-of-lock test (receiver.metrics.loss_of_lock: running-mean Doppler / code
    error against the generator's truth) agrees with the truth-free lock_lost_channels: none."""
    from ultratight.receiver.cli.metrics import loss_of_lock, tracking_errors
    with h5py.File(rec["out"] / "res.h5") as f, h5py.File(rec["gen"] / "ph.truth.h5") as tr:
        prns = [int(p) for p in f.attrs["prn"]]
        cols = [list(tr.attrs["prn"]).index(p) for p in prns]
        t0 = f["t_start_s"][()]
        d_err, code_err = tracking_errors(t0, f["doppler_hz"][()], f["code_phase_chips"][()], tr["t_s"][()],
                                          tr["doppler_hz"][()][:, cols], tr["code_phase_chips"][()][:, cols])
    t_mid = t0 + 0.5e-3
    lost = loss_of_lock(t0, d_err, code_err)
    assert np.all(np.isnan(lost)), dict(zip(prns, lost))
    late = (t_mid > t_mid[0, 0] + 1.0) & np.isfinite(d_err) & np.isfinite(code_err)   # truth ends at 20 s
    assert late.sum() > 0.9 * late.size
    # docs/ultratight.md "Start-up without truth": tracking on the first row against the truth,
    # Doppler 0.015 Hz and code 0.0056 chip RMS (from 1 s after the hand-over). This run (seed 1):
    # 0.0140 Hz, 0.0046 chip; seeds 1-3: 0.0140-0.0209 Hz, 0.0031-0.0046 chip.
    # Bounds = documented x 1.5: above every seed, and a doubled figure breaks them
    assert np.sqrt(np.mean(d_err[late] ** 2)) < 1.5 * 0.015
    assert np.sqrt(np.mean(code_err[late] ** 2)) < 1.5 * 0.0056          # chips


def test_csv_kml_nmea_rinex_outputs(rec):
    out = rec["out"]
    with h5py.File(out / "res.h5") as f:
        n_sins = f["sins/t_s"].shape[0]
        t = f["sins/t_s"][()]
        eul = f["sins/euler"][()]
    lines = (out / "nav.csv").read_text().splitlines()
    assert lines[0].startswith("# ultratight") and lines[1].startswith("t_s,gps_week,gps_tow_s,x_m")
    rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[2:]])
    assert rows.shape[0] == n_sins
    assert np.allclose(rows[:, 0], t) and np.allclose(rows[:, 14], np.degrees(eul[:, 2]))
    tow0 = rec["sidecar"]["start_tow_s"]
    assert np.allclose(rows[:, 2], tow0 + t - rows[:, 15] / 299792458.0, atol=1e-9)     # GPS time
    nmea = (out / "nav.nmea").read_text().splitlines()
    gga = [ln for ln in nmea if ln.startswith("$GPGGA")]
    assert len(gga) == pytest.approx(n_sins / 10, abs=2)        # NMEA at 10 Hz
    assert all(re.search(r",1,13,\d+\.\d\d,", ln) for ln in gga)   # fix quality 1, 13 channels, HDOP
    assert "<coordinates>" in (out / "nav.kml").read_text()


def test_rinex_pseudoranges_against_truth(rec):
    obs = (rec["out"] / "ut.obs").read_text().splitlines()
    end = next(i for i, ln in enumerate(obs) if "END OF HEADER" in ln)
    assert any("C1C L1C D1C S1C" in ln for ln in obs[:end])
    with h5py.File(rec["gen"] / "ph.truth.h5") as tr:
        prn = [int(p) for p in tr.attrs["prn"]]
        ts, pr_t, dop_t = tr["t_s"][()], tr["pseudorange_m"][()], tr["doppler_hz"][()]
    tow0 = rec["sidecar"]["start_tow_s"]
    err_pr, err_d, n_ep = [], [], 0
    t_rx = None
    for ln in obs[end + 1:]:
        if ln.startswith(">"):
            f = ln[1:].split()
            t_rx = int(f[3]) * 3600 + int(f[4]) * 60 + float(f[5])       # 2022-01-01 00:00 = TOW 518400
            n_ep += 1
            continue
        c = prn.index(int(ln[1:3]))
        pr, dop = float(ln[3:17]), float(ln[35:49])
        t = 518400.0 + t_rx - tow0
        err_pr.append(pr - np.interp(t, ts, pr_t[:, c]))
        err_d.append(dop - np.interp(t, ts, dop_t[:, c]))
    assert n_ep >= 10 * (DURATION_S - rec["summary"]["handover"]["handover_t_s"]) - 3
    assert np.sqrt(np.mean(np.square(err_pr))) < 3.0
    assert np.sqrt(np.mean(np.square(err_d))) < 0.5


def test_init_flags_start(rec, capsys, tmp_path):
    """All three --init-* flags: the engine starts at --start from exactly them (clock taken as zero,
    sigmas FLAG_SIGMAS) without a scalar pass; --prn is then needed (the sidecar has no list)."""
    from ultratight.receiver.deep.handover import FLAG_SIGMAS
    with h5py.File(rec["gen"] / "ph.traj.h5") as g:
        k = int(np.argmin(np.abs(g["t"][()] - 2.0)))
        lat, lon, h = (float(v) for v in g["llh"][k])
        ve, vn, vu = (float(v) for v in g["vel_l"][k])
        r, p, y = (float(v) for v in np.degrees(g["euler"][k]))
    u = rec["user"]
    out = tmp_path / "flags.h5"
    rc = main(["process", str(u / "rec.ci16"), "--mode", "ultratight", "--imu", str(u / "imu.csv"), "--ephemeris",
               str(u / "nav.rnx"), "--prn", ",".join(str(p_) for p_ in rec["sidecar"]["prn"]), "--start", "2",
               "--duration", "4", "--json", "--out", str(out), "--init-llh",
               f"{math.degrees(lat)!r},{math.degrees(lon)!r},{h!r}", "--init-vel", f"{ve!r},{vn!r},{vu!r}",
               "--init-att", f"{r!r},{p!r},{y!r}", *BITS_FLAGS])
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    assert s["startup"] == "init-flags" and s["handover"]["handover_t_s"] == pytest.approx(2.0)
    assert "scalar_pass" not in s["handover"]
    assert s["lock_lost_channels"] == []
    assert s["duration_s"] == pytest.approx(2.0, abs=5e-3)        # --duration counts from the file start
    with h5py.File(out) as f, h5py.File(rec["gen"] / "ph.traj.h5") as g:
        assert f["sins/t_s"][0] == pytest.approx(2.0, abs=1e-12)
        assert np.allclose(f["sins/llh"][0], [lat, lon, h], rtol=0, atol=1e-9)
        assert np.allclose(f["sins/vel_l"][0], [ve, vn, vu], atol=1e-9)
        assert np.allclose(np.degrees(f["sins/euler"][0]), [r, p, y], atol=1e-6)
        assert np.allclose(f["sins/clk"][0], 0.0)
        assert np.allclose(f["sins/sigma_pos_l_m"][0], FLAG_SIGMAS["pos_m"])
        t = f["sins/t_s"][()]
        from ultratight.ins.earth import llh_to_ecef_batch
        e = np.linalg.norm(llh_to_ecef_batch(f["sins/llh"][()]) - _truth_at(g, t, "pos_e"), axis=1)
    # started from the truth with the flags' stated 10 m: it stays within that statement
    assert e.max() < 3.0 * FLAG_SIGMAS["pos_m"]


@pytest.mark.parametrize("flag,value,needle", [
    ("--init-llh", "28.2,102.0", "--init-llh: expected three numbers"),
    ("--init-vel", "1,x,3", "--init-vel: 'x' is not a number"),
    ("--init-att", "0,95,0", "--init-att: pitch must be in [-90, 90] deg"),
    ("--init-llh", "28,nan,0", "--init-llh: 'nan' is not a finite number"),
])
def test_malformed_init_flags(rec, flag, value, needle):
    u = rec["user"]
    msg = _one_line_error(_cli("process", str(u / "rec.ci16"), "--mode", "ultratight", "--imu", str(u / "imu.csv"),
                               "--ephemeris", str(u / "nav.rnx"), flag, value))
    assert needle in msg


def test_scalar_pass_without_fix(rec):
    """A PRN that is not in the signal: the scalar pass acquires nothing -> one line, exit 2."""
    u = rec["user"]
    msg = _one_line_error(_cli("process", str(u / "rec.ci16"), "--mode", "ultratight", "--imu", str(u / "imu.csv"),
                               "--ephemeris", str(u / "nav.rnx"), "--prn", "3"))
    assert "start-up: the scalar pass" in msg and "found no fix" in msg


def test_startup_flags_need_ultratight_mode(rec):
    msg = _one_line_error(_cli("process", str(rec["user"] / "rec.ci16"), "--init-att=-1,2,3"))
    assert "--init-att only used with --mode ultratight" in msg


def test_parse_init_flags_negative_values_and_units():
    from ultratight.receiver.deep.handover import parse_init_flags
    from ultratight.ins.attitude import quat_to_euler
    o = parse_init_flags("-33.87,151.21,40", "-1,2,0.5", "-10,5,270")
    assert np.allclose(o["llh"], [math.radians(-33.87), math.radians(151.21), 40.0])
    assert np.allclose(o["vel_l"], [-1.0, 2.0, 0.5])
    assert np.allclose(np.degrees(quat_to_euler(o["q_lb"])), [-10.0, 5.0, 270.0])


def test_truth_start_needs_truth(rec):
    u = rec["user"]
    msg = _one_line_error(_cli("process", str(u / "rec.ci16"), "--mode", "ultratight", "--imu", str(u / "imu.csv"),
                               "--ephemeris", str(u / "nav.rnx"), "--startup", "truth-perturbed"))
    assert "start-up truth-perturbed needs the truth in the IMU file" in msg


# ------------------------------------------------------------------ attitude alignment (closed form)
def _rot(seed):
    from ultratight.ins.attitude import euler_to_dcm
    rng = np.random.default_rng(seed)
    return np.asarray(euler_to_dcm(*rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 2 * np.pi])))


def test_wahba_recovers_rotation_and_covariance():
    from ultratight.receiver.deep.handover import wahba
    C = _rot(3)
    n1, n2 = np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.9, 0.1])
    C_est, P = wahba([(n1, C.T @ n1, 1e-3), (n2, C.T @ n2, 1e-2)])
    assert np.allclose(C_est, C, atol=1e-12)
    # orthogonal unit vectors: P = diag(s2^2, s1^2..) in the frame of the vectors (closed form)
    e1, e2 = np.eye(3)[0], np.eye(3)[1]
    _, P2 = wahba([(e1, C.T @ e1, 0.01), (e2, C.T @ e2, 0.02)])
    inv = 1.0 / np.array([0.02 ** -2, 0.01 ** -2, 0.01 ** -2 + 0.02 ** -2])
    assert np.allclose(P2, np.diag(inv), rtol=1e-12)


def _still_imu(C_lb, llh, grade, seconds=2.0, rate=100.0):
    from ultratight.ins.earth import earth_rate_l, gravity_l
    from ultratight.ins.imu_data import ImuData
    n = int(seconds * rate)
    f_b = C_lb.T @ -np.asarray(gravity_l(llh[0], llh[2]))
    w_b = C_lb.T @ np.asarray(earth_rate_l(llh[0]))
    t = (np.arange(n) + 1) / rate
    return ImuData(t=t, dtheta_b=np.tile(w_b / rate, (n, 1)), dv_b=np.tile(f_b / rate, (n, 1)), rate_hz=rate,
                   meta={"grade": grade})


@pytest.mark.parametrize("grade", ["navigation", "mems"])
def test_still_alignment_levelling_and_gyro_compass(grade):
    from ultratight.errors import ConfigError
    from ultratight.ins.attitude import quat_to_dcm
    from ultratight.ins.imu import imu_errors_from_config
    from ultratight.receiver.deep.handover import HandoverConfig, attitude_at
    llh = np.array([math.radians(41.3), math.radians(2.0), 50.0])
    C = _rot(5)
    imu = _still_imu(C, llh, grade)
    err = imu_errors_from_config({"preset": grade, "rate_hz": 100.0})
    args = (imu, err, 2.0, llh, np.zeros(3), np.zeros(3), 0.01, HandoverConfig())
    if grade == "mems":
        # 200 deg/h gyro bias vs 11 deg/h horizontal Earth rate: refused, one line naming the way out
        with pytest.raises(ConfigError, match=r"gyro-compassing gives a heading sigma of .* give the heading with "
                                              r"--init-att"):
            attitude_at(*args)
        return
    q, P, method, _ = attitude_at(*args)
    assert method == "levelling+gyro-compass"
    assert np.allclose(quat_to_dcm(q), C, atol=1e-9)             # noise-free increments: exact
    sig = np.degrees(np.sqrt(np.diag(P)))
    assert sig[2] < 1.0 and sig[0] < 0.01 and sig[1] < 0.01     # heading from the Earth rate, tilt from gravity


def test_coordinated_bank_left_axis():
    """The body's left axis in coordinated flight: horizontal in straight flight; a right turn with a
    centripetal acceleration of g banks 45 deg right wing down (the left axis tilts up)."""
    from ultratight.receiver.deep.handover import coordinated_left
    g = 9.81
    np.testing.assert_allclose(coordinated_left([200.0, 0.0, 0.0], [50.0, 0.0, 0.0], g), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(coordinated_left([0.0, 100.0, 5.0], [0.0, 3.0, 0.0], g)[2], 0.0, atol=1e-12)
    h = math.sqrt(0.5)
    np.testing.assert_allclose(coordinated_left([100.0, 0.0, 0.0], [0.0, -g, 0.0], g), [0.0, h, h], atol=1e-12)
    np.testing.assert_allclose(coordinated_left([100.0, 0.0, 0.0], [0.0, g, 0.0], g), [0.0, h, -h], atol=1e-12)


def _fixes(n, still_until_s, rate_hz=10.0, fs=4e6, seed=7):
    """Synthetic 10 Hz scalar fixes: positions scattered about a point, still until ``still_until_s``,
    a clock with a constant drift (the engine clock of every fix the same when carried along it)."""
    rng = np.random.default_rng(seed)
    p0 = np.array([6378137.0, 0.0, 0.0])
    out = []
    for i in range(n):
        t = i / rate_hz
        v = np.zeros(3) if t <= still_until_s else np.array([0.0, 5.0, 0.0])
        # receiver time of the sample minus GPS time: clock 100 m + 0.2 m/s
        gps = 1000.0 + t - (100.0 + 0.2 * t) / 299792458.0
        out.append({"sample_index": round(t * fs), "pos_e": p0 + rng.normal(0.0, 2.0, 3), "vel_e": v, "n_used": 8,
                    "gps_tow_s": gps, "gps_week": 2190, "clk_drift_mps": 0.2})
    return out


def test_still_receiver_averages_its_fixes_up_to_fix_avg_s():
    """A still receiver hands over at the fix ending fix_avg_s of still fixes with their mean; motion
    after 5 s: the mean of the 5 s it has; motion before fix_avg_min_s: the settled fix alone."""
    from dataclasses import replace

    from ultratight.receiver.deep.handover import HandoverConfig, _engine_clock, _still_fixes

    cfg, fs = HandoverConfig(), 4e6
    fx = _fixes(200, 100.0)
    j, mean, sig, used = _still_fixes(fx, 10, fs, cfg)
    assert j == 10 + round(cfg.fix_avg_s * 10) and len(used) == j - 10 + 1
    np.testing.assert_allclose(mean, np.mean([f["pos_e"] for f in fx[10:j + 1]], axis=0), rtol=0, atol=1e-9)
    assert 1.0 < sig < 3.0                              # the scatter (2 m per axis), not scatter / sqrt(n)
    clocks = [_engine_clock(f, fs, 1000.0, 2190, j / 10.0) for f in used]
    np.testing.assert_allclose(clocks, 100.0 + 0.2 * j / 10.0, atol=1e-4)    # each fix's clock carried to t_j
    j5, _, _, used5 = _still_fixes(_fixes(200, 5.0), 10, fs, cfg)
    assert j5 == 50 and len(used5) == 41               # still up to 5.0 s: 4 s of them from the fix at 1 s
    jm, mean_m, _, used_m = _still_fixes(_fixes(200, 3.0), 10, fs, cfg)
    assert (jm, mean_m, used_m) == (10, None, None)    # still for 2 s after the settled fix: < fix_avg_min_s
    jp, mean_p, _, _ = _still_fixes(_fixes(200, 30.0), 10, fs, replace(cfg, fix_avg_s=3.0))
    assert jp == 40 and mean_p is not None             # the earlier 3 s mean


def test_still_fixes_ride_through_velocity_noise_but_not_a_creep():
    """30 dB-Hz fixes scatter by 0.2 m/s: a fix at 0.25 m/s with sigma 0.22 m/s is still rest; a
    vehicle creeping at 0.3 m/s with the same noise is not still, however noisy each fix is."""
    from ultratight.receiver.deep.handover import HandoverConfig, _still_fixes

    cfg, fs = HandoverConfig(), 4e6
    fx = _fixes(200, 100.0)
    rng = np.random.default_rng(3)
    for f in fx:
        f["vel_e"] = rng.normal(0.0, 0.22 / math.sqrt(3.0), 3)
        f["sigma_vel_mps"] = 0.22
    fx[15]["vel_e"] = np.array([0.25, 0.0, 0.0])
    j, mean, _, _ = _still_fixes(fx, 10, fs, cfg)
    assert j == 110 and mean is not None
    for f in fx:
        f["vel_e"] = f["vel_e"] + np.array([0.0, 0.3, 0.0])
    assert _still_fixes(fx, 10, fs, cfg)[1] is None
