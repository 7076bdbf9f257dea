"""The double loop on a user's recorded files: an IF file (with its sidecar) and an IMU file (HDF5 or
CSV with its declaration). Checks that the two belong together in time, selects the ephemerides,
chooses the initial state (given, from flags, from the scalar receiver's first fix, or from the
IMU file's truth) and runs :class:`~ultratight.receiver.deep.engine.UltratightEngine` from the
hand-over on (docs/process.md, docs/ultratight.md).
"""

import json
from pathlib import Path

import numpy as np

from ultratight.errors import ConfigError, InputFileError
from ultratight.fusion.coupling import tight as tightmod
from ultratight.ins import imu_decl
from ultratight.receiver.deep.engine import UltratightEngine
from ultratight.receiver.deep.methods import DEFAULT_METHOD, method_spec
from ultratight.receiver.deep.startup import StartupErrors, perturb_state
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.rinex import read_rinex_nav

IMU_IF_TOLERANCE_S = 1e-3      # largest accepted IMU/IF start-time mismatch
PREDICTED_MASK_DEG = 5.0       # elevation mask of the satellites tracked after a start without scalar pass


def _imu_start_tow(imu):
    """GPS time (week, tow) of the IMU's t = 0, when the file says (None otherwise)."""
    meta = getattr(imu, "meta", None) or {}
    if "start_tow_s" in meta:
        return meta.get("start_week"), float(meta["start_tow_s"])
    cfg = meta.get("config_json")
    if isinstance(cfg, str):
        try:
            cfg = json.loads(cfg)
        except ValueError:
            cfg = None
    if isinstance(cfg, dict) and isinstance(cfg.get("time"), dict) and "tow_s" in cfg["time"]:
        return cfg["time"].get("week"), float(cfg["time"]["tow_s"])
    return None


def check_imu_if_alignment(src, imu, if_path="IF file", imu_path="IMU file", tol_s=IMU_IF_TOLERANCE_S):
    """Check that the IMU data can drive the SINS over the IF record; returns the usable duration.

    * stamps: finite, strictly increasing, no gaps (also checked by the IMU readers);
    * the IMU time axis starts at the first IF sample: ``t0 == 0`` and, when the IMU file carries
      a GPS start time, it equals the IF start time within ``tol_s``;
    * the IMU covers at least one SINS step of the IF record.
    Raises InputFileError naming the file and the offending values.
    """
    t = np.asarray(imu.t, dtype=float)
    if t.size < 2 or not np.all(np.isfinite(t)):
        raise InputFileError(f"{imu_path}: IMU time stamps missing or not finite")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0]) + 1
        raise InputFileError(f"{imu_path}: sample {i}: out-of-order or duplicate time stamp t = {t[i]!r} s "
                             f"(previous {t[i - 1]!r} s)")
    dt = 1.0 / float(imu.rate_hz)
    if np.any(np.abs(d - dt) > 0.25 * dt):
        i = int(np.flatnonzero(np.abs(d - dt) > 0.25 * dt)[0]) + 1
        raise InputFileError(f"{imu_path}: sample {i}: interval {d[i - 1]:.6g} s at t = {t[i]!r} s differs from "
                             f"the nominal {dt:.6g} s ({imu.rate_hz} Hz): gap or irregular sampling")
    t0 = float(getattr(imu, "t0", t[0] - dt))
    if abs(float(t[0]) - dt) > tol_s:
        raise InputFileError(f"{imu_path}: first IMU stamp t = {float(t[0]):.6g} s; the first increment must end "
                             f"one IMU interval ({dt:.6g} s) after the first IF sample (t = 0): IMU/IF time offset "
                             f"{float(t[0]) - dt:+.6g} s")
    if abs(t0) > tol_s:
        raise InputFileError(f"{imu_path}: IMU time axis starts at t0 = {t0:.6g} s but must start at the first IF "
                             f"sample (t0 = 0 within {tol_s} s); IMU/IF time offset {t0:.6g} s")
    st = _imu_start_tow(imu)
    if st is not None and src.start_tow_s is not None:
        w_imu, tow_imu = st
        off = tow_imu - float(src.start_tow_s)
        if w_imu is not None and src.start_week is not None:
            off += (int(w_imu) - int(src.start_week)) * 604800.0
        if abs(off) > tol_s:
            raise InputFileError(f"{imu_path}: IMU starts at GPS TOW {tow_imu:.6f} s but {if_path} starts at "
                                 f"{float(src.start_tow_s):.6f} s: IMU/IF time offset {off:+.6f} s "
                                 f"(tolerance {tol_s} s)")
    usable = min(src.duration_s, float(t[-1]))
    if usable < 2 * dt:
        raise InputFileError(f"{imu_path}: IMU data end at t = {t[-1]:.6g} s; they must cover the IF record "
                             f"({src.duration_s:.6g} s)")
    return usable


def run_ultratight_on_files(if_path, imu_path, method=DEFAULT_METHOD, meta=None, nav_path=None, prns=None,
                            init_state=None, options=None, duration_s=None, seed=0, startup_errors=None,
                            imu_declaration=None, startup="auto", init_overrides=None, start_s=0.0,
                            handover=None, iono="klobuchar", tropo="saastamoinen", imu_noise=None):
    """Run the ultra-tight engine on a recorded IF file and an IMU file (HDF5 or CSV).

    * ``meta``: sidecar/ION metadata for the IF file (default ``IFFILE.json``); the IF start time
      (``start_week``/``start_tow_s``) is required.
    * Ephemerides: ``nav_path`` (RINEX) or, for generator files, the sidecar's scenario
      (nominal constellation).  PRNs: ``prns`` (``--prn``) or the satellites the start-up finds:
      every one the scalar pass kept tracking, or, without a scalar pass, those the ephemerides put
      above 5° at the initial position; satellites the navigation file marks unhealthy or has no
      ephemeris for are skipped with one warning line each.
    * Initial state (``startup``: ``auto`` | ``scalar-fix`` | ``truth-perturbed``; the source used
      is ``result.info["startup_source"]``):

      - ``init_state`` dict (``llh``, ``vel_l``, ``q_lb``, ``clk_bias_m``, ``clk_drift_mps``) given
        by the caller: used as it is, at ``start_s`` (``init-state``);
      - ``init_overrides`` with all of ``llh``, ``vel_l``, ``q_lb`` (the ``--init-*`` flags,
        :func:`ultratight.receiver.deep.handover.parse_init_flags`): those at ``start_s``, clock zero
        (``init-flags``);
      - otherwise (``auto``, the default, and ``scalar-fix``) the scalar receiver's first fixes from
        ``start_s`` on (``scalar-fix``, :func:`ultratight.receiver.deep.handover.scalar_handover`,
        configured by ``handover``), the flags in ``init_overrides`` replacing their part;
      - only when named (``truth-perturbed``, an *assisted* start for generated files): the IMU
        file's truth at t0 perturbed by ``startup_errors`` (seeded by ``seed``), the sidecar's PRN
        list.  No other start-up reads the IMU file's truth group.

      The engine starts at the hand-over time (an IMU stamp): the IF source and the IMU data are
      seen from there on (:class:`~ultratight.receiver.deep.handover.SourceWindow`,
      :func:`~ultratight.receiver.deep.handover.imu_window`), the channels from predicted code phase
      and Doppler (no acquisition); the result's times are shifted back to seconds since the first
      sample of the file.
    * IMU conventions: ``imu_declaration`` (sidecar keys, :mod:`ultratight.ins.imu_decl`) over the
      IMU file's sidecar; a GPS-stamped IMU is cut to the IF start; time alignment checked by
      :func:`check_imu_if_alignment`.  The filter is tuned from the declared IMU
      (:func:`_declared_model`; ``imu_noise``: the noise flags' table).
    * Atmosphere (``iono``, ``tropo`` as the scalar receiver's flags): the engine's predictions and the
      scalar start-up carry the same model (:func:`_atmosphere`).
    Returns an :class:`EngineResult`.
    """
    from ultratight.receiver.deep import handover as ho
    _check_method_and_startup(method, startup)
    src, imu, imu_path, dur, warnings = _open_recording(if_path, imu_path, meta, imu_declaration, duration_s,
                                                        imu_noise)
    if startup != ho.STARTUP_TRUTH:
        imu.truth = None            # a generated IMU file's truth group is read only by the named truth start-up
    side = src.meta or {}
    gen_cfg = side.get("generator") if isinstance(side.get("generator"), dict) else None
    week, tow0 = int(src.start_week), float(src.start_tow_s)
    nav, ephs = _file_ephemerides(if_path, nav_path, gen_cfg, week, tow0)
    given = prns is not None
    if startup == ho.STARTUP_TRUTH and prns is None:
        prns = side.get("prn")      # the generator's list: part of the assisted start-up
    prns = _drop_unhealthy(nav, prns, week, tow0, warnings)
    atmo, iono_source = _atmosphere(nav, gen_cfg, iono, tropo)
    start_s = float(start_s or 0.0)
    if not 0.0 <= start_s < dur:
        raise ConfigError(f"--start {start_s:g} s is outside the usable record (0 .. {dur:.3f} s)")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    source, hand, t_h, init_state, prns = _startup(
        src, imu, imu_path, nav if nav is not None else ephs, ephs, prns, startup, init_state,
        dict(init_overrides or {}), start_s, handover, gen_cfg, startup_errors, rng, atmo)
    atmo, iono_source, tropo_note = _after_startup(hand, warnings, (nav, gen_cfg, iono), atmo, iono_source,
                                                   (source == ho.STARTUP_TRUTH, handover))
    prns = _tracked_prns(prns, given, source, hand, init_state, (nav, ephs, nav_path, week, tow0, t_h), warnings,
                         if_path)
    file_start = {"week": int(week), "tow_s": float(tow0)}
    res, opt, t_h = _run_reinitialising(
        (src, imu, ephs, [int(p) for p in prns], method, options, rng, dur, atmo, iono_source),
        (nav if nav is not None else ephs, handover), init_state, t_h, warnings)
    res.info["warnings"] = list(warnings)
    res.info["assisted"] = assisted_parts(source, opt.bits) + ([tropo_note] if tropo_note else [])
    _note_start(res, t_h, source, hand, file_start)
    t_mid = file_start["tow_s"] + t_h + 0.5 * res.duration_s
    res.info["sat_pos_e"] = [np.asarray(sat_state(ephs[int(p)], np.array([t_mid]))[0][0]).tolist() for p in prns]
    return res


def _run_reinitialising(run, scalar, init_state, t_h, warnings):
    """The engine from the hand-over at ``t_h`` on; when its integrity monitor declares the solution
    lost (receiver.deep.integrity, docs/ultratight.md "Integrity") the run stops there, a new scalar
    fix is taken from that time on (:func:`~ultratight.receiver.deep.handover.scalar_handover`, same
    satellites) and a new engine runs from it — at most ``max_reinit`` times, then the result ends
    lost. ``run``: the recording, ``(src, imu, ephs, prns, method, options, rng, duration, atmosphere,
    iono source)``; ``scalar``: ``(ephemerides of the scalar pass, HandoverConfig)``. Returns the runs
    joined in time (:func:`~ultratight.receiver.deep.recorder.join_results`), the engine options
    used and the first hand-over time."""
    from dataclasses import replace

    from ultratight.receiver.deep import handover as ho
    from ultratight.receiver.deep.integrity import IntegrityThresholds
    from ultratight.receiver.deep.options import EngineOptions
    from ultratight.receiver.deep.recorder import join_results
    src0, imu0, ephs, prns, method, options, rng, dur, atmo, iono_source = run
    opt = options or EngineOptions()
    opt = replace(opt, integrity_stop=True if opt.integrity_stop is None else bool(opt.integrity_stop))
    max_reinit = IntegrityThresholds.from_options(opt.integrity).max_reinit
    parts, starts = [], []
    while True:
        src, imu = src0, imu0
        if t_h > 0.0:
            src, imu, t_h = _from_handover(src0, imu0, t_h, dur)
        eng = UltratightEngine(src, imu, ephs, prns, int(src.start_week), float(src.start_tow_s), method=method,
                               options=opt, init_state=init_state, rng=rng, duration_s=dur - t_h, atmosphere=atmo,
                               iono_source=iono_source)
        parts.append(eng.run())
        starts.append(t_h)
        lost = (parts[-1].info.get("integrity") or {}).get("lost_at_s")
        if lost is None or not opt.integrity_stop or len(parts) > max_reinit:
            break
        t_lost = t_h + float(lost)
        try:
            hand = ho.scalar_handover(src0, imu0, tightmod.imu_errors_from_meta(imu0), scalar[0], prns,
                                      start_s=t_lost, cfg=scalar[1], atmosphere=atmo)
        except ConfigError as exc:
            warnings.append(f"integrity lost at t = {t_lost:.1f} s; no re-initialisation: {exc}")
            break
        t_h = hand["t_s"]
        init_state = {k: hand[k] for k in ("llh", "vel_l", "q_lb", "clk_bias_m", "clk_drift_mps", "sigmas",
                                           "code_phase_chips") if k in hand}
        if t_h >= dur - 1.0:
            warnings.append(f"integrity lost at t = {t_lost:.1f} s; no re-initialisation: the scalar fix came at "
                            f"t = {t_h:.1f} s, too close to the end ({dur:.1f} s)")
            break
    return join_results(parts, starts), opt, starts[0]


def assisted_parts(startup_source, bits):
    """What of a run was assisted by the generator's knowledge (empty for a run on a user's files):
    the named truth start-up and the bits re-encoded from the ephemeris (valid for the project's own
    generated LNAV only).  Every output of such a run says so (docs/process.md)."""
    from ultratight.receiver.deep import handover as ho
    out = []
    if startup_source == ho.STARTUP_TRUTH:
        out.append("start-up from the IMU file's truth (truth-perturbed)")
    if bits == "assisted":
        out.append("data bits re-encoded from the ephemeris (--bits assisted)")
    return out


def _open_recording(if_path, imu_path, meta, imu_declaration, duration_s, noise=None):
    """``(src, imu, imu_path, duration, warnings)``: the IF file (its start time required), the IMU file
    read in its declared conventions and cut to the IF start, the duration both cover, and a warning
    line when the IMU ends before the IF span asked for."""
    src = open_if(if_path, meta=meta)
    if src.start_tow_s is None or src.start_week is None:
        raise InputFileError(f"{if_path}: the IF start time (start_week, start_tow_s) is unknown; "
                             "give it in the sidecar/metadata")
    imu_path = Path(imu_path)
    # the IMU's declared conventions (sidecar IMU.csv.json + ``imu_declaration`` overrides, ins.imu_decl)
    imu = imu_decl.read_imu_file(imu_path, imu_declaration)
    imu = imu_decl.align_to_gps_start(imu, src.start_week, src.start_tow_s, imu_path)
    warnings = _declared_model(imu, imu_path, noise)
    usable = check_imu_if_alignment(src, imu, if_path, imu_path)
    dur = usable if duration_s is None else min(float(duration_s), usable)
    wanted = src.duration_s if duration_s is None else min(float(duration_s), src.duration_s)
    if dur < wanted - 1.0 / float(imu.rate_hz):
        warnings.append(f"{imu_path.name}: the IMU data end at t = {dur:.3f} s, before the {wanted:.3f} s of "
                        f"{Path(if_path).name} asked for: only the first {dur:.3f} s are processed")
    return src, imu, imu_path, dur, warnings


def _declared_model(imu, imu_path, noise=None):
    """The IMU model the tight filter is tuned from (``meta["errors"]``): the noise table ``noise``
    (grade and datasheet figures, :mod:`ultratight.ins.imu_noise`; from flags) key by key over the
    declaration's ``noise`` table; without either, the model the file itself declares (a generated
    file).  Returns the warning lines: an IMU declared with no noise at all is filtered as the
    "paper" IMU of Zhao et al. 2014 (navigation grade), which is said."""
    meta = imu.meta if imu.meta is not None else {}
    imu.meta = meta
    table = dict((meta.get("declaration") or {}).get("noise") or {})
    table.update({k: v for k, v in (noise or {}).items() if v is not None})
    if isinstance(meta.get("errors"), dict) and not noise:
        return []
    if not table:
        return [f"{Path(imu_path).name}: no IMU noise declared (sidecar 'noise' table or --imu-grade): the "
                "filter assumes the navigation-grade 'paper' IMU of Zhao et al. 2014"]
    from ultratight.ins.imu_noise import error_model_of, imu_noise
    grade = table.pop("grade", None)
    meta["errors"] = error_model_of(imu_noise(grade, **table)).to_dict()
    return []


def _note_start(res, t_h, source, hand, file_start):
    """Times of ``res`` shifted back to seconds since the file's first sample; the start-up recorded."""
    if t_h > 0.0:
        res.t_start = res.t_start + t_h
        res.nav_t = res.nav_t + t_h
        if res.sins:
            res.sins["t_s"] = res.sins["t_s"] + t_h
    res.info["startup_source"] = source
    res.info["t_offset_s"] = float(t_h)
    res.info["handover"] = (hand or {}).get("startup", {"source": source, "handover_t_s": float(t_h)})
    res.info["if_file_start"] = file_start          # the result's times count from this receiver time


def _drop_unhealthy(nav, prns, week, tow0, warnings):
    """``prns`` without the satellites whose only ephemerides at the start the navigation file marks
    unhealthy (one warning line naming each and its 6-bit SV health); ``prns`` as given otherwise."""
    if nav is None or not prns:
        return prns
    sick = {}
    for p in prns:
        if nav.select(int(p), week, tow0, True) is None:
            e = nav.select(int(p), week, tow0, False)
            if e is not None:
                sick[int(p)] = int(e.sv_health)
    if sick:
        warnings.append("skipped as unhealthy in the navigation file: " +
                        ", ".join(f"PRN {p} (SV health {h})" for p, h in sick.items()))
    return [p for p in prns if int(p) not in sick]


def _tracked_prns(prns, given, source, hand, init_state, nav_at, warnings, if_path):
    """The satellites the engine tracks (:func:`run_ultratight_on_files`, "PRNs"): given ones the
    scalar pass saw, else those the start-up found, less the unhealthy ones and those without an
    ephemeris (warning lines); ConfigError when none is left or a given one has no ephemeris."""
    from ultratight.receiver.deep import handover as ho
    nav, ephs, nav_path, week, tow0, t_h = nav_at
    if given and source == ho.STARTUP_SCALAR:
        prns = _tracked_of(prns, hand, warnings)
    if not given and source != ho.STARTUP_SCALAR and not prns:
        prns = _predicted_prns(ephs, init_state, week, tow0 + t_h)
    if not given:
        prns = _drop_unhealthy(nav, prns, week, tow0, warnings)
        prns = _drop_without_ephemeris(prns, ephs, nav_path, warnings)
    if not prns:
        raise ConfigError(f"{if_path}: no satellites to track: the start-up found none with a healthy ephemeris "
                          "(give them with --prn)")
    missing = [p for p in prns if p not in ephs]
    if missing:
        raise ConfigError(f"no ephemeris for PRN {missing} at the IF start (week {week}, TOW {tow0:.3f} s) in "
                          f"{nav_path if nav_path is not None else 'the nominal constellation'}")
    return prns


def _tracked_of(prns, hand, warnings):
    """The given ``prns`` that the start-up's scalar pass kept tracking; the others are left out
    with one warning line (the engine starts its channels from the scalar channels' code phases:
    a satellite the scalar pass did not see would be a channel on noise)."""
    tracked = {int(p) for p in hand["startup"]["scalar_pass"]["tracked"]}
    unseen = [int(p) for p in prns if int(p) not in tracked]
    if unseen:
        warnings.append("left out, not tracked by the start-up's scalar pass: " +
                        ", ".join(f"PRN {p}" for p in unseen))
    return [int(p) for p in prns if int(p) in tracked]


def _drop_without_ephemeris(prns, ephs, nav_path, warnings):
    """``prns`` without the satellites that have no ephemeris valid at the start (one warning line
    naming them): the start-up found them, the navigation data cannot predict them."""
    none = [int(p) for p in prns or () if int(p) not in ephs]
    if none:
        warnings.append(f"skipped, no ephemeris at the start in "
                        f"{nav_path if nav_path is not None else 'the nominal constellation'}: "
                        + ", ".join(f"PRN {p}" for p in none))
    return [int(p) for p in prns or () if int(p) in ephs]


def _predicted_prns(ephs, state, week, tow_s, mask_deg=PREDICTED_MASK_DEG):
    """The satellites the ephemerides put above ``mask_deg`` at the initial position of ``state``
    (a start-up without a scalar pass: ``--init-*`` flags or a given state)."""
    from ultratight.ins.earth import llh_to_ecef
    from ultratight.signals.geometry import visible_prns
    lat, lon, h = (float(v) for v in state["llh"])
    return [int(p) for p in visible_prns(ephs, np.asarray(llh_to_ecef(lat, lon, h)), week, tow_s, mask_deg)]


def _file_ephemerides(if_path, nav_path, gen_cfg, week, tow0):
    """``(nav, ephs)`` of a recording: the RINEX file's ephemerides valid at the start (``nav`` the
    parsed file) or, for a generator file on the nominal constellation, the nominal ones (``nav``
    None)."""
    if nav_path is not None:
        nav = read_rinex_nav(nav_path)
        return nav, nav.select_all(week, tow0)
    if gen_cfg is not None and gen_cfg.get("satellites", {}).get("source", "nominal") == "nominal":
        return None, nominal_ephemerides(week, tow0)
    raise ConfigError(f"{if_path}: no ephemerides: give a RINEX navigation file (--ephemeris)")


def _check_method_and_startup(method, startup):
    """One line (ConfigError) for a method that needs no IMU or an unknown start-up."""
    from ultratight.receiver.deep import handover as ho
    if not method_spec(method).needs_imu:
        raise ConfigError(f"method {method!r} is the scalar receiver: use `ultratight process` without "
                          f"--mode ultratight")
    if startup not in ("auto", ho.STARTUP_SCALAR, ho.STARTUP_TRUTH):
        raise ConfigError(f"unknown start-up {startup!r}; expected auto, {ho.STARTUP_SCALAR} or {ho.STARTUP_TRUTH}")


def _after_startup(hand, warnings, how, atmo, iono_source, truth_start):
    """The start-up's warnings added to ``warnings``; the run's ``(atmosphere, iono source, assisted
    note or None)``: without the troposphere when the scalar hand-over found the signal carries none
    (receiver.deep.tropo_check), or, after the truth-perturbed start-up (``truth_start`` = (True, its
    hand-over configuration or None)), when the generator put none on it (:func:`truth_start_troposphere`);
    ``how`` = ``(nav, generator config, iono)`` of :func:`_atmosphere`."""
    warnings.extend((hand or {}).get("warnings") or [])
    if ((hand or {}).get("troposphere") or {}).get("troposphere") == "absent":
        return (*_atmosphere(*how, "off"), None)
    is_truth, handover = truth_start
    if is_truth:
        return truth_start_troposphere(handover, how, atmo, iono_source)
    return atmo, iono_source, None


def truth_start_troposphere(handover, how, atmo, iono_source):
    """The troposphere of a run with the truth-perturbed (assisted) start-up, which has no scalar fixes
    to test the recording with (:mod:`ultratight.receiver.deep.tropo_check`): when the correction was
    not asked for (``handover.tropo_check``, true by default) and the generator's configuration in the
    sidecar put no troposphere on the signal (:func:`~ultratight.receiver.deep.atmosphere_terms.
    scenario_model`, as a scenario run reads it), the correction is off — knowledge of the generator, so
    the returned note joins the run's assisted parts. ``(atmosphere, iono source, note or None)``;
    ``how`` = ``(nav, generator config, iono)`` of :func:`_atmosphere`."""
    from ultratight.receiver.deep.atmosphere_terms import scenario_model
    from ultratight.receiver.deep.handover import HandoverConfig
    gen_cfg = how[1]
    if not (handover or HandoverConfig()).tropo_check or not isinstance(gen_cfg, dict) \
            or getattr(atmo, "tropo", "off") == "off" or getattr(scenario_model(gen_cfg), "tropo", "off") != "off":
        return atmo, iono_source, None
    atmo, iono_source = _atmosphere(*how, "off")
    return atmo, iono_source, ("troposphere correction off: the generator's configuration (sidecar) put none on "
                               "the signal (the truth-perturbed start-up has no fixes to test it on)")


def _atmosphere(nav, gen_cfg, iono, tropo):
    """``(AtmosphereModel, source of alpha/beta)`` of a recording's run (``iono``: klobuchar | off,
    ``tropo``: saastamoinen | off; :mod:`ultratight.receiver.deep.atmosphere_terms`): the Klobuchar
    coefficients from the RINEX header of the navigation file or, for a generated file, the broadcast
    values its sidecar records (:func:`~ultratight.receiver.deep.atmosphere_terms.broadcast_of_generator`);
    without either the ionosphere stays off (recorded as ``klobuchar (no parameters)``)."""
    from ultratight.receiver.deep.atmosphere_terms import broadcast_of_generator, receiver_model
    alpha = beta = source = None
    if iono != "off":
        if nav is not None and nav.ion_alpha and nav.ion_beta:
            alpha, beta, source = tuple(nav.ion_alpha), tuple(nav.ion_beta), "rinex"
        else:
            alpha, beta = broadcast_of_generator(gen_cfg)
            source = "sidecar" if alpha is not None else None
    return receiver_model(iono=iono, tropo=tropo, alpha=alpha, beta=beta), source


def _startup(src, imu, imu_path, nav_or_ephs, ephs, prns, startup, init_state, overrides, start_s, handover,
             gen_cfg, startup_errors, rng, atmo=None):
    """The initial state of a recording's run (:func:`run_ultratight_on_files`, "Initial state"):
    ``(source, hand, t_h, init_state, prns)`` — the start-up source's name, the scalar or flags
    hand-over (or None), its time (s since the first sample), the state and the PRNs to track."""
    from ultratight.receiver.deep import handover as ho
    tr = getattr(imu, "truth", None)
    has_truth = bool(tr) and "llh" in tr
    t_h = 0.0
    source = "init-state"
    hand = None
    if init_state is not None:
        t_h = start_s
    elif all(k in overrides for k in ("llh", "vel_l", "q_lb")):
        hand = ho.flags_state(overrides, start_s)
        source = ho.STARTUP_FLAGS
    elif startup == ho.STARTUP_TRUTH:
        if not has_truth:
            raise ConfigError(f"{imu_path}: start-up {ho.STARTUP_TRUTH} needs the truth in the IMU file (none here)")
        if start_s != 0.0:
            raise ConfigError(f"start-up {ho.STARTUP_TRUTH} starts at the first sample: --start not supported")
        source = ho.STARTUP_TRUTH
        rcv = (gen_cfg or {}).get("receiver", {})
        truth0 = {"llh": np.asarray(tr["llh"][0]), "vel_l": np.asarray(tr["vel_l"][0]),
                  "q_lb": np.asarray(tr["q_lb"][0]), "clk_bias_m": float(rcv.get("clock_bias_m", 0.0)),
                  "clk_drift_mps": float(rcv.get("clock_drift_mps", 0.0))}
        init_state = perturb_state(truth0, startup_errors or StartupErrors(), rng)
    else:
        hand = ho.scalar_handover(src, imu, tightmod.imu_errors_from_meta(imu), nav_or_ephs,
                                  prns, start_s=start_s, cfg=handover, overrides=overrides, atmosphere=atmo)
        source = ho.STARTUP_SCALAR
        if not prns:
            # every satellite the scalar pass kept tracking (not only the hand-over fix's)
            prns = [int(p) for p in hand["startup"]["scalar_pass"]["tracked"]]
    if hand is not None:
        t_h = hand["t_s"]
        init_state = {k: hand[k] for k in ("llh", "vel_l", "q_lb", "clk_bias_m", "clk_drift_mps", "sigmas",
                                           "code_phase_chips") if k in hand}
    return source, hand, t_h, init_state, prns


def _from_handover(src, imu, t_h, dur):
    """The IF source and IMU data seen from the hand-over time ``t_h`` on (rounded to an IMU stamp):
    ``(src, imu, t_h)``."""
    from ultratight.receiver.deep import handover as ho
    dt_imu = 1.0 / float(imu.rate_hz)
    t_h = float(getattr(imu, "t0", 0.0)) + round((t_h - float(getattr(imu, "t0", 0.0))) / dt_imu) * dt_imu
    if t_h >= dur - 2 * dt_imu:
        raise ConfigError(f"start-up at t = {t_h:.3f} s leaves no record to process (usable {dur:.3f} s)")
    n0 = int(round(t_h * src.fs_hz))
    return ho.SourceWindow(src, n0), ho.imu_window(imu, t_h), t_h
