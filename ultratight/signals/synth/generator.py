"""GPS L1 C/A sampled-IF signal generator (streaming): one generation of a resolved scenario, block
by block, into the IF file, its sidecar and the truth files.

The signal model, the per-interval geometry and the numba synthesis kernels are in
:mod:`ultratight.signals.synth.synthesis`; the front end (filter, AGC, quantiser) in
:mod:`ultratight.signals.synth.frontend`. Here: the satellites and C/N0 of a scenario, the
``[atmosphere]`` table (applied by the signal plan), the noise (with its events) and the truth
writer.

Horizon (``satellites.horizon_deg``, opt-in): satellites rising above ``mask_deg`` during the
run are generated as well, and every satellite's amplitude is zero while its elevation is below
``horizon_deg`` (terrain or obstructions; 0 = the open horizon); the truth ``cn0_dbhz`` keeps the
configured value.

Random numbers: one ``numpy.random.Generator`` from the seed
(``SeedSequence(seed).spawn(2)``: noise, IMU); noise is drawn block by block with
``standard_normal(dtype=float32)`` in a fixed block size, so a seed always gives the same file.
:class:`Generation` holds one generation's fixed part; every pass over its blocks
(:meth:`Generation.blocks`) starts a new noise generator from the noise sequence and the front-end
filter from rest, so :func:`generate` and :class:`ultratight.signals.synth.ifstream.GeneratedIf` (the same
samples handed to a receiver in memory, without a file) agree bit for bit.

Outputs (see docs/generator.md for the schema): ``<stem>.<format>`` IF file and its
``.json`` sidecar, ``<stem>.truth.h5``, and when the scenario has ``[imu]``,
``<stem>.imu.h5`` and ``<stem>.traj.h5``. Everything is written to temporary names and
renamed at the end; a failure removes the temporaries.
"""

import errno
import json
import os
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from ultratight import __version__
from ultratight.errors import ConfigError
from ultratight.ins import imu as imu_mod
from ultratight.ins.imu_data import write_imu_h5
from ultratight.ins.trajectory import build_trajectory
from ultratight.io_guard import StagedFile, describe_os_error, os_errno
from ultratight.signals.atmosphere import AtmosphereModel
from ultratight.signals.constellation import ephemerides_for
from ultratight.signals.synth.frontend import FrontEnd
from ultratight.signals.synth.synthesis import COS_LUT, SIN_LUT, SignalPlan, _synth_complex, _synth_real
from ultratight.signals.geometry import visible_prns
from ultratight.signals.recording.iffile import IfWriter, check_bits_for_format, get_format
from ultratight.signals.lnav import nav_bits, nav_bits_mode
from ultratight.signals.lnav_message import IonoUtc, quantise_iono

BLOCK_INTERVALS = 100             # intervals per generated block (fixed: reproducibility)


# ------------------------------------------------------------------------------------------
# run configuration helpers
# ------------------------------------------------------------------------------------------
def _ephemerides(cfg, rx_pos0_e):
    sat = cfg.get("satellites", {})
    week, tow = int(cfg["time"]["week"]), float(cfg["time"]["tow_s"])
    source = sat.get("source", "nominal")
    if source in ("nominal", "rinex"):
        ephs = ephemerides_for(cfg)
    else:
        raise ConfigError(f"satellites.source must be 'nominal' or 'rinex', got {source!r}")
    prns = list(sat.get("prns", []) or [])
    if prns:
        missing = [p for p in prns if p not in ephs]
        if missing:
            raise ConfigError(f"satellites.prns: no ephemeris for PRN {missing} from source {source!r}")
    else:

        prns = visible_prns(ephs, rx_pos0_e, week, tow, float(sat.get("mask_deg", 5.0)),
                            max_count=sat.get("max_count"))
        if sat.get("horizon_deg") is not None:
            # satellites rising above the mask during the run are generated too (their signal
            # starts at the horizon, see generate())
            step = 30.0
            for k in range(1, int(float(cfg.get("duration_s", 0.0)) // step) + 1):
                for p in visible_prns(ephs, rx_pos0_e, week, tow + k * step, float(sat.get("mask_deg", 5.0))):
                    if p not in prns:
                        prns.append(p)
        if not prns:
            raise ConfigError("satellites: no satellite visible above mask_deg at the start point")
    cn0 = sat.get("cn0_dbhz", 45.0)
    if isinstance(cn0, (list, tuple)):
        if len(cn0) != len(prns):
            raise ConfigError(f"satellites.cn0_dbhz has {len(cn0)} values for {len(prns)} satellites")
    return [ephs[p] for p in prns], np.broadcast_to(np.asarray(cn0, float), (len(prns),)).copy()


def atmosphere_from_config(atm):
    """(AtmosphereModel or None, lnav_message.IonoUtc or None) of a validated ``[atmosphere]`` table."""
    if not atm:
        return None, None

    alpha, beta = atm["alpha"], atm["beta"]
    if atm["broadcast"]:
        # the delays the receiver can reproduce are those of the transmitted (quantised) coefficients
        alpha, beta = quantise_iono(alpha, beta)
    model = AtmosphereModel(iono=atm["iono"], alpha=alpha, beta=beta, tropo=atm["tropo"],
                            mapping_name=atm["tropo_mapping"], iono_scale=atm["iono_scale"])
    bc = IonoUtc(alpha=tuple(alpha), beta=tuple(beta)) if atm["broadcast"] else None
    return model, bc


def set_nav_bits(plan, duration_s, enabled, mode="lnav", seed=0):
    """Fetch the data bits covering the run for every satellite of ``plan`` into ``plan.bits`` (none
    when not ``enabled``: all +1); ``mode``: the content
    (:data:`ultratight.signals.lnav.NAV_DATA_MODES`), random parts drawn from ``seed``; with
    ``plan.iono_broadcast`` its parameters are sent in subframe 4 page 18."""
    plan.bits = {}
    if not enabled:
        return

    first = int(math.floor((plan.tow0 - 0.2) / 0.02))
    n_bits = int(math.ceil((duration_s + 0.5) / 0.02)) + 2
    for eph in plan.ephs:
        kw = {"iono": plan.iono_broadcast} if plan.iono_broadcast is not None else {}
        if mode == "lnav":
            b = np.asarray(nav_bits(eph, plan.week, first * 0.02, n_bits, **kw), dtype=np.int8)
        else:
            b = np.asarray(nav_bits_mode(eph, plan.week, first * 0.02, n_bits, mode, seed, **kw), dtype=np.int8)
        plan.bits[int(eph.prn)] = (first, b)


def noise_factor(events, e):
    """Noise std factor at receiver-clock seconds ``e`` (array) from [[noise_events]] (those at the IF:
    ``place`` "if", the default; the others act inside the receiver)."""
    f = np.ones(np.shape(e), dtype=np.float32)
    for ev in events or []:
        if ev.get("place", "if") != "if":
            continue
        inside = (e >= ev["t0_s"]) & (e < ev["t1_s"])
        f[inside] *= np.float32(ev["noise_factor"])
    return f


class _NoiseAhead:
    """The unit Gaussian noise of the generator's blocks, drawn from ``rng`` in block order (the same
    stream as drawing each block when it is needed) one block ahead by a second thread, into two
    alternating buffers, so the draw overlaps the synthesis, filtering and writing of the block
    before (numpy's generator releases the GIL while it fills an array)."""

    def __init__(self, rng, max_len, sizes):
        self._rng = rng
        self._bufs = [np.empty(max_len, dtype=np.float32), np.empty(max_len, dtype=np.float32)]
        self._sizes = list(sizes)
        self._k = 0
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._next = self._submit(0)

    def _submit(self, k):
        if k >= len(self._sizes):
            return None
        x = self._bufs[k % 2][:self._sizes[k]]
        return self._pool.submit(self._rng.standard_normal, out=x, dtype=np.float32)

    def next(self):
        """The next block's noise (float32 view of a buffer, valid until the next-but-one call)."""
        x = self._next.result()
        self._k += 1
        self._next = self._submit(self._k)
        return x

    def close(self):
        self._pool.shutdown(wait=True, cancel_futures=True)


class _TruthWriter:
    """Appends per-interval truth rows to an HDF5 file (resizable, chunked datasets)."""

    def __init__(self, path, nsat, attrs):

        self.staged = StagedFile(path)
        self.path, self.tmp = self.staged.path, self.staged.tmp
        self.f = None
        try:
            self._create(h5py, nsat, attrs)
        except BaseException:          # also an interruption while the file is being set up
            self.abort()
            raise

    def _create(self, h5py, nsat, attrs):
        # no chunk cache: the rows come in whole chunks (FLUSH_ROWS), and with HDF5's default cache the
        # writer's memory grew by the file's size (about 70 MB for a 60 s paper-highdyn run), kept after close
        self.f = h5py.File(self.tmp, "w", rdcc_nbytes=0)
        for k, v in attrs.items():
            self.f.attrs[k] = v
        self.n = 0
        self._held, self._n_held = [], 0
        self.ds = {}
        spec = {"t_s": (), "sample_index": (), "tow_s": (), "t_true_tow_s": (), "pos_e": (3,),
                "vel_e": (3,), "clk_bias_m": (), "clk_drift_mps": (), "noise_factor": (),
                "code_phase_chips": (nsat,), "carrier_phase_cycles": (nsat,), "doppler_hz": (nsat,),
                "cn0_dbhz": (nsat,), "nav_bit": (nsat,), "pseudorange_m": (nsat,), "elev_deg": (nsat,),
                "azim_deg": (nsat,), "t_tx_tow_s": (nsat,), "iono_m": (nsat,), "tropo_m": (nsat,)}
        for name, shp in spec.items():
            dt = np.int8 if name == "nav_bit" else (np.int64 if name == "sample_index" else np.float64)
            self.ds[name] = self.f.create_dataset(name, shape=(0,) + shp, maxshape=(None,) + shp,
                                                  chunks=(1000,) + shp, dtype=dt)

    FLUSH_ROWS = 5000     # rows held before they are written (one resize and write per dataset; whole chunks)

    def append(self, rows):
        self._held.append(rows)
        self._n_held += len(rows["t_s"])
        if self._n_held >= self.FLUSH_ROWS:
            self._flush()

    def _flush(self):
        if not self._held:
            return
        m = self._n_held
        try:
            for k, d in self.ds.items():
                d.resize(self.n + m, axis=0)
                d[self.n:self.n + m] = np.concatenate([r[k] for r in self._held], axis=0)
        except (RuntimeError, OSError) as exc:
            raise self._write_error(exc) from None
        self.n += m
        self._held, self._n_held = [], 0

    def write_sent_bits(self, sent, nav_data):
        """Every data bit sent (docs/generator.md): ``sent`` = (nav_bit0, (nsat, n_bits) int8 ±1) of
        :meth:`SignalPlan.sent_bits`; bit k of row s starts at GPS week ``week``, TOW
        (nav_bit0 + k) * 20 ms of satellite time. ``nav_data``: the data mode."""
        self.f.attrs["nav_data"] = nav_data
        self.f.attrs["nav_bit0"] = int(sent[0])
        self.f.create_dataset("nav_bits", data=sent[1], compression="gzip", compression_opts=1)

    def finish(self):
        self._flush()
        try:
            self.f.close()
        except (RuntimeError, OSError) as exc:
            raise self._write_error(exc) from None

    def _write_error(self, exc):
        """An HDF5 write failure (full disk, file-size limit) as the OSError it is, errno included (HDF5
        reports it as a RuntimeError quoting ``errno = N``)."""
        if isinstance(exc, OSError) and exc.errno:
            return exc
        code = os_errno(exc)
        return OSError(code or errno.EIO, describe_os_error(exc), str(self.tmp))

    def abort(self):
        try:
            if self.f is not None:
                self.f.close()
        except Exception:
            pass
        self.staged.discard()


def output_paths(out_dir, stem, fmt):
    out_dir = Path(out_dir)
    return {"if": out_dir / f"{stem}.{fmt}", "meta": out_dir / f"{stem}.{fmt}.json",
            "truth": out_dir / f"{stem}.truth.h5", "imu": out_dir / f"{stem}.imu.h5",
            "trajectory": out_dir / f"{stem}.traj.h5"}


def generation_estimate(cfg):
    """Up-front estimate of a generation: ``{"if_bytes", "truth_bytes", "imu_bytes", "memory_bytes"}``.

    IF bytes = duration x fs x sample size; truth: one row (~40 numbers + 12 per satellite) per
    1 ms interval, in whole chunks of 1000 rows; IMU + trajectory: ~40 numbers per IMU sample (written from memory)."""
    fe = cfg["frontend"]
    spec = get_format(fe["format"])
    n = float(cfg["duration_s"]) * float(fe["fs_hz"])
    if_bytes = spec.nbytes(n, spec.layout())
    n_sat = max(len(cfg["satellites"].get("prns") or []), int(cfg["satellites"].get("max_count", 12)))
    rows = float(cfg["duration_s"]) * 1000.0
    if math.isfinite(rows):
        rows = math.ceil(rows / 1000.0) * 1000.0            # the truth datasets hold whole 1000-row chunks
    truth_bytes = rows * 8 * (12 + 12 * n_sat)
    imu_rows = float(cfg["duration_s"]) * float((cfg.get("imu") or {}).get("rate_hz", 0.0)) if cfg.get("imu") else 0.0
    imu_bytes = imu_rows * 8 * 40
    # the generator's plan holds per-interval polynomial coefficients for a block, the IMU whole
    memory = 3 * imu_bytes + 64e6
    return {"if_bytes": if_bytes, "truth_bytes": truth_bytes, "imu_bytes": imu_bytes, "memory_bytes": memory}


def _progress(total, enabled, desc):
    if not enabled or not sys.stderr.isatty():
        return None
    return tqdm(total=total, unit="s", desc=desc, leave=False,
                bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}]")


class Generation:
    """The fixed parts of one generation of a resolved scenario ``cfg`` and seed (front end, sample
    format, signal plan, noise events, sizes, the seed's noise and IMU sequences), and its blocks.

    :func:`generate` writes them to files; :class:`ultratight.signals.synth.ifstream.GeneratedIf` hands the
    samples to a receiver without a file. Both run :meth:`blocks`, which starts from the first
    block with a fresh noise generator and front-end state on every call, so every pass over a
    generation yields the same samples."""

    def __init__(self, cfg, seed=None, ephemerides=None, trajectory=None):
        fe_cfg = cfg.get("frontend", {})
        fe = FrontEnd.from_config(fe_cfg)
        if fe.gain_mode == "fixed" and "headroom" not in fe_cfg:
            # fixed gain without an explicit headroom: the loudest noise event must fit the clip level
            fe.headroom = max([1.0] + [float(ev["noise_factor"]) for ev in cfg.get("noise_events", []) or []
                                       if ev.get("place", "if") == "if"])
        fmt = fe_cfg.get("format", "ci8" if fe.is_complex else "i8")
        spec = get_format(fmt)
        if spec.is_complex != fe.is_complex:
            raise ConfigError(f"frontend.format {fmt!r} is {'complex' if spec.is_complex else 'real'} but "
                              f"frontend.sampling is {'complex' if fe.is_complex else 'real'}")
        check_bits_for_format(spec.name, fe.bits)
        duration = float(cfg.get("duration_s", 0))
        if not duration > 0:
            raise ConfigError(f"duration_s must be > 0, got {cfg.get('duration_s')}")
        seed = cfg.get("seed", 0) if seed is None else seed
        self.seed = int(seed)
        self.ss_noise, self.ss_imu = np.random.SeedSequence(self.seed).spawn(2)
        week, tow0 = int(cfg["time"]["week"]), float(cfg["time"]["tow_s"])
        rcv = cfg.get("receiver", {})
        if trajectory is None:

            trajectory = build_trajectory(cfg.get("trajectory", {"kind": "static"}), rcv, duration)
        if ephemerides is None:
            p0, _ = trajectory.pos_vel_e(np.zeros(1))
            ephs, cn0 = _ephemerides(cfg, p0[0])
        else:
            ephs = list(ephemerides)
            cn0 = np.broadcast_to(np.asarray(cfg.get("satellites", {}).get("cn0_dbhz", 45.0), float),
                                  (len(ephs),)).copy()
        atmosphere, iono_broadcast = atmosphere_from_config(cfg.get("atmosphere"))
        plan = SignalPlan(ephs, cn0, trajectory, week, tow0, fe.fs_hz, fe.if_hz, fe.is_complex, fe.inversion,
                          rcv.get("clock_bias_m", 0.0), rcv.get("clock_drift_mps", 0.0),
                          atmosphere=atmosphere, iono_broadcast=iono_broadcast)
        self.nav_data = cfg.get("nav", {}).get("data", "lnav")
        set_nav_bits(plan, duration, bool(cfg.get("nav", {}).get("data_bits", True)), self.nav_data, self.seed)
        self.cfg, self.fe, self.spec, self.plan, self.trajectory = cfg, fe, spec, plan, trajectory
        self.week, self.tow0, self.duration = week, tow0, duration
        self.events = cfg.get("noise_events", [])
        self.horizon = cfg.get("satellites", {}).get("horizon_deg")
        self.n_total = int(round(duration * fe.fs_hz))
        self.n_int_total = -(-self.n_total // plan.L)
        self.resolved = json.loads(json.dumps(cfg, default=str))
        self.resolved["seed"] = self.seed

    def sidecar_extra(self):
        """The generator's entries of the IF sidecar (beside the format fields)."""
        return {"generator": self.resolved, "prn": self.plan.prns.tolist(),
                "cn0_dbhz": self.plan.cn0_dbhz.tolist(), "frontend": self.fe.to_dict()}

    def block_starts(self):
        """First interval of every block (blocks of :data:`BLOCK_INTERVALS` intervals)."""
        return range(0, self.n_int_total, BLOCK_INTERVALS)

    def blocks(self, samples=True, truth=True, synth=None):
        """Yield ``(j0, n_valid, y, rows)`` per block of :data:`BLOCK_INTERVALS` intervals from the first:
        ``j0`` the block's first interval, ``n_valid`` its samples, ``y`` the quantised samples
        (complex64 / float32 on the quantiser's integer levels, or None without ``samples``; valid
        until the next block is asked for) and ``rows`` the truth rows of its intervals (or None
        without ``truth``). ``synth``: the (complex, real) synthesis kernels (default those of
        :mod:`ultratight.signals.synth.synthesis`)."""
        plan, fe, events, horizon = self.plan, self.fe, self.events, self.horizon
        L, n_total, n_int_total = plan.L, self.n_total, self.n_int_total
        synth_c, synth_r = synth or (_synth_complex, _synth_real)
        nsat = len(plan.ephs)
        comps = 2 if fe.is_complex else 1
        fe.reset()                       # the front-end filter starts from rest on every pass
        noise = None
        if samples:
            noise = _NoiseAhead(np.random.default_rng(self.ss_noise), BLOCK_INTERVALS * L * comps,
                                [min(BLOCK_INTERVALS, n_int_total - j) * L * comps for j in self.block_starts()])
        try:
            for j0 in self.block_starts():
                n_int = min(BLOCK_INTERVALS, n_int_total - j0)
                ns = n_int * L
                n_valid = min(ns, n_total - j0 * L)
                coefs, epoch0, starts, rx0 = plan.coefficients(j0, n_int)
                bits = plan.bit_values(epoch0)
                y = None
                if samples:
                    amps = np.broadcast_to(plan.amp, (n_int, nsat)).astype(np.float32)
                    if horizon is not None and nsat:
                        # terrain / obstructions block the satellites below the horizon elevation
                        el = np.stack([g["elev_rad"] for g in starts], 1)
                        amps = amps * (el > math.radians(float(horizon))).astype(np.float32)
                    x = noise.next()      # this block's unit noise (drawn while the last block was processed)
                    t_b0, t_b1 = j0 * L / fe.fs_hz, (j0 * L + ns) / fe.fs_hz
                    fac = None
                    if any(ev["t0_s"] < t_b1 and ev["t1_s"] > t_b0 for ev in events):
                        fac = noise_factor(events, (j0 * L + np.arange(ns)) / fe.fs_hz)
                    if fac is not None and np.any(fac != 1.0):
                        if comps == 2:
                            x.reshape(-1, 2)[...] *= fac[:, None]
                        else:
                            x *= fac
                    if nsat:
                        if fe.is_complex:
                            synth_c(x.reshape(-1, 2), L, n_int, plan.codes, coefs, amps, bits, COS_LUT, SIN_LUT)
                        else:
                            synth_r(x, L, n_int, plan.codes, coefs, amps, bits, COS_LUT)
                    y = x.view(np.complex64) if fe.is_complex else x
                    y = y[:n_valid]
                    y = fe.filter(y)
                    sig_now = 1.0 if fac is None else fac[:n_valid]
                    if fac is not None and np.all(fac[:n_valid] == fac[0]):
                        sig_now = float(fac[0])
                    y = fe.quantize_block(y, sig_now)
                rows = self._truth_rows(j0, n_int, starts, rx0, bits) if truth else None
                yield j0, n_valid, y, rows
        finally:
            if noise is not None:
                noise.close()

    def _truth_rows(self, j0, n_int, starts, rx0, bits):
        """Truth rows of the intervals ``j0 .. j0 + n_int - 1`` (at the interval starts)."""
        plan, fe, L = self.plan, self.fe, self.plan.L
        nsat = len(plan.ephs)
        e0 = (j0 + np.arange(n_int)) * L / fe.fs_hz
        nf = noise_factor(self.events, e0)
        rows = {"t_s": e0, "sample_index": (j0 + np.arange(n_int)) * L, "tow_s": self.tow0 + e0,
                "t_true_tow_s": rx0["t_true"], "pos_e": rx0["pos_e"], "vel_e": rx0["vel_e"],
                "clk_bias_m": rx0["clk_bias_m"], "clk_drift_mps": np.full(n_int, plan.drift),
                "noise_factor": nf}
        none = np.zeros((n_int, 0))
        rows["code_phase_chips"] = np.stack([g["code_phase_chips"] for g in starts], 1) if nsat else none
        rows["carrier_phase_cycles"] = np.stack([g["carrier_phase_cycles"] for g in starts], 1) if nsat else none
        rows["doppler_hz"] = np.stack([g["doppler_hz"] for g in starts], 1) if nsat else none
        rows["pseudorange_m"] = np.stack([g["pseudorange_m"] for g in starts], 1) if nsat else none
        rows["elev_deg"] = np.degrees(np.stack([g["elev_rad"] for g in starts], 1)) if nsat else none
        rows["azim_deg"] = np.degrees(np.stack([g["azim_rad"] for g in starts], 1)) if nsat else none
        rows["t_tx_tow_s"] = np.stack([g["t_tx_tow"] for g in starts], 1) if nsat else none
        for k in ("iono_m", "tropo_m"):
            rows[k] = (np.stack([g[k] for g in starts], 1) if nsat and k in starts[0]
                       else np.zeros((n_int, nsat)))
        rows["cn0_dbhz"] = plan.cn0_dbhz[None, :] - 20.0 * np.log10(nf.astype(float))[:, None]
        rows["nav_bit"] = bits[:, :, 0].astype(np.int8)
        return rows


def generate(cfg, out_dir, stem, seed=None, progress=True, ephemerides=None, trajectory=None, write_if=True,
             write_rest=True):
    """Generate the IF file, sidecar, truth (and IMU/trajectory) for a resolved scenario ``cfg``.

    ``seed`` overrides ``cfg['seed']``. ``ephemerides`` (list of Ephemeris, with
    ``cfg['satellites']['cn0_dbhz']`` scalar or per-satellite) and ``trajectory`` (an object
    with ``pos_vel_e(t)``) may be given to bypass the scenario's own sources. Returns a dict of
    the written paths (keys ``if, meta, truth`` and, with ``[imu]``, ``imu, trajectory``) plus
    ``summary`` (dict). ``write_if=False`` writes everything but the IF file and its sidecar (no
    samples are synthesised: the truth does not depend on them) — for a receiver fed by
    :class:`ultratight.signals.synth.ifstream.GeneratedIf` of the same configuration and seed.
    ``write_rest=False`` writes the IF file and its sidecar only (no truth, IMU or trajectory: for a
    data set that has them already; the samples are the same).
    """
    t_start = time.perf_counter()
    gen = Generation(cfg, seed, ephemerides, trajectory)
    fe = gen.fe

    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise ConfigError(f"output directory does not exist: {out_dir}")
    paths = output_paths(out_dir, stem, gen.spec.name)
    writer = files = blocks = None
    bar = _progress(gen.duration, progress, f"generate {stem}")
    try:
        if write_if:
            writer = IfWriter(paths["if"], gen.spec.name, fe.fs_hz, fe.if_hz, inversion=fe.inversion,
                              start_week=gen.week, start_tow_s=gen.tow0, bits=fe.bits, extra=gen.sidecar_extra())
        files = GenerationFiles(gen, paths, t_start) if write_rest else None
        blocks = gen.blocks(samples=write_if, truth=write_rest)
        for _j0, n_valid, y, rows in blocks:
            if writer is not None:
                writer.write(y, exact=fe.bits != 0)   # quantiser levels fit every integer format allowed
            if files is not None:
                files.append(rows)
            if bar is not None:
                bar.update(n_valid / fe.fs_hz)
        result = {"if": paths["if"], "meta": paths["meta"]} if write_if else {}
        if files is not None:
            files.finish()
        if writer is not None:
            writer.close()
        if files is not None:
            result.update(files.commit())
    except BaseException:
        if writer is not None:
            writer.abort()
        if files is not None:
            files.abort()
        raise
    finally:
        if blocks is not None:
            blocks.close()
        if bar is not None:
            bar.close()
    result["summary"] = _summary(gen, write_if, t_start)
    return result


class GenerationFiles:
    """The files of generation ``gen`` but the IF, at ``paths`` (:func:`output_paths`), staged until
    :meth:`commit`: the truth, whose rows come block by block (:meth:`append`, the ``rows`` of
    :meth:`Generation.blocks`), and, with the scenario's ``[imu]``, the IMU and trajectory files, written
    when this object is made (the sensor drawn for the run goes into the truth file) — so a receiver can
    read the IMU while the samples and the truth are still being generated. ``t_start``: the
    generation's start (``time.perf_counter()``), for the truth's ``elapsed_s``."""

    def __init__(self, gen, paths, t_start=None):
        self.gen, self.paths = gen, paths
        self.t_start = time.perf_counter() if t_start is None else t_start
        self.truth = _TruthWriter(paths["truth"], len(gen.plan.ephs), _truth_attrs(gen))
        self.extra = []
        self._early = []             # files committed before the truth (commit_imu)
        self.written = {"truth": paths["truth"]}
        try:
            imu_cfg = gen.cfg.get("imu")
            if imu_cfg and hasattr(gen.trajectory, "save_h5"):
                self.extra += _write_imu_traj(imu_cfg, gen.trajectory, paths, gen.ss_imu, gen.resolved, self.truth.f)
                self.written.update(imu=paths["imu"], trajectory=paths["trajectory"])
        except BaseException:
            self.abort()
            raise

    def commit_imu(self):
        """The IMU and trajectory files renamed onto their paths now (they are complete), for a receiver
        that runs while the truth is generated (:meth:`abort` removes them again)."""
        for staged in self.extra:
            staged.commit()
            self._early.append(staged.path)
        self.extra = []

    def append(self, rows):
        self.truth.append(rows)

    def finish(self):
        """The truth completed (its data bits, the elapsed time) and closed."""
        sent = self.gen.plan.sent_bits()
        if sent is not None:
            self.truth.write_sent_bits(sent, self.gen.nav_data)
        self.truth.f.attrs["elapsed_s"] = time.perf_counter() - self.t_start
        self.truth.finish()

    def commit(self):
        """Every file renamed onto its path (after :meth:`finish`); returns the paths by key."""
        self.truth.staged.commit()
        for staged in self.extra:
            staged.commit()
        return dict(self.written)

    def abort(self):
        """Every file of the generation removed (staged, or committed ahead by :meth:`commit_imu`)."""
        self.truth.abort()
        for staged in self.extra:
            staged.discard()
        for path in self._early:
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass


def _truth_attrs(gen):
    """Attributes of the truth file of generation ``gen``: resolved scenario, front end, time base,
    satellites, seed, size and schema."""
    fe, plan = gen.fe, gen.plan
    return {"config_json": json.dumps(gen.resolved), "version": __version__, "fs_hz": fe.fs_hz,
            "if_hz": fe.if_hz, "is_complex": fe.is_complex, "inversion": fe.inversion,
            "format": gen.spec.name, "week": gen.week, "tow0_s": gen.tow0, "samples_per_row": plan.L,
            "prn": plan.prns, "cn0_dbhz_config": plan.cn0_dbhz, "seed": gen.seed,
            "n_samples": gen.n_total, "schema": "ultratight generator truth v1 (docs/generator.md)"}


def _summary(gen, write_if, t_start):
    """The ``summary`` entry of :func:`generate`'s result (``t_start``: its ``time.perf_counter()``)."""
    fe, plan = gen.fe, gen.plan
    return {"prns": plan.prns.tolist(), "cn0_dbhz": plan.cn0_dbhz.tolist(),
            "n_samples": gen.n_total, "duration_s": gen.n_total / fe.fs_hz, "fs_hz": fe.fs_hz,
            "if_hz": fe.if_hz, "format": gen.spec.name, "seed": gen.seed, "if_written": bool(write_if),
            "elapsed_s": time.perf_counter() - t_start}


def _write_imu_traj(imu_cfg, trajectory, paths, ss_imu, resolved, truth_f=None):
    """Write IMU and trajectory truth under temporary names; returns their :class:`StagedFile` objects.

    The IMU file's metadata holds the sensor's declaration (the ``[imu]`` table read by
    :func:`ultratight.ins.imu.imu_errors_from_config`); the sensor drawn from it for this seed goes
    into the open truth file ``truth_f`` (group ``imu_errors``, :func:`write_imu_errors_truth`)."""

    rate = float(imu_cfg.get("rate_hz", 100.0))
    errors = imu_mod.imu_errors_from_config(imu_cfg)
    lever = imu_cfg.get("lever_arm_m")
    data = imu_mod.synthesize_imu(trajectory, rate, errors, np.random.default_rng(ss_imu),
                                  lever_arm_b=None if lever is None else np.asarray(lever, float))
    if truth_f is not None:
        write_imu_errors_truth(truth_f, data.errors_realised)
    out = [StagedFile(paths["imu"])]
    write_imu_h5(out[0].tmp, data, {"config_json": json.dumps(resolved), "version": __version__})
    out.append(StagedFile(paths["trajectory"]))
    trajectory.save_h5(out[1].tmp, rate)
    return out


# the drawn sensor errors in the truth file (group imu_errors): SI, per body axis (FLU)
IMU_TRUTH_KEYS = ("gyro_bias", "accel_bias", "gyro_sf", "accel_sf", "gyro_misalign", "accel_misalign")


def write_imu_errors_truth(f, realised):
    """Group ``imu_errors`` of the open truth file ``f``: the sensor errors drawn for the run
    (``realised``: :attr:`ultratight.ins.imu_data.ImuData.errors_realised`) -- biases rad/s and
    m/s^2, scale factors, misalignments rad -- for the evaluation; the receiver reads the IMU file's
    declaration, never these."""
    g = f.create_group("imu_errors")
    g.attrs["description"] = ("sensor errors drawn for this run from the [imu] declaration (truth): biases "
                              "rad/s, m/s^2; scale factors; misalignments rad; body axes FLU")
    for k in IMU_TRUTH_KEYS:
        g.create_dataset(k, data=np.asarray(realised[k], float))


def read_imu_errors_truth(path):
    """The drawn sensor errors of a truth file (:func:`write_imu_errors_truth`), or None when the
    run had no IMU (or the file predates the group)."""
    with h5py.File(path, "r") as f:
        if "imu_errors" not in f:
            return None
        return {k: np.asarray(f["imu_errors"][k][()], float) for k in IMU_TRUTH_KEYS if k in f["imu_errors"]}


__all__ = ["generate", "generation_estimate", "Generation", "GenerationFiles", "noise_factor", "output_paths",
           "set_nav_bits", "read_imu_errors_truth", "write_imu_errors_truth"]
