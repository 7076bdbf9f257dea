"""``results.h5`` of ``ultratight scenario`` (docs/ultratight.md): per run and method the estimates, tracking
errors, arbitration modes and navigation solution, with the resolved configuration as attributes, written
atomically (:func:`ultratight.io_guard.write_h5_atomic`). The arrays are compressed on threads
(:mod:`ultratight.h5deflate`), each (run, method) as soon as its result is in (:func:`pack_result`)."""

import json
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np

from ultratight import __version__
from ultratight.cores import allowed_cores
from ultratight.h5deflate import Deflated
from ultratight.io_guard import write_h5_atomic

SCHEMA = "ultratight scenario results v1 (docs/ultratight.md)"


def deflate_pool():
    """A thread pool for :func:`pack_result`: one thread per core this process may use."""
    return ThreadPoolExecutor(max_workers=allowed_cores(), thread_name_prefix="results-deflate")


def pack_result(res, d_err, c_err, pool):
    """One (run, method) entry of ``results.h5``: its attributes and its arrays as :class:`ultratight.
    h5deflate.Deflated`, compressed on ``pool`` from now on (the arrays must not change meanwhile)."""
    attrs = {"prn": np.asarray(res.prns, dtype=np.int64), "runtime_s": float(res.runtime_s),
             "info_json": json.dumps(res.info, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))}
    arrays = {k: Deflated(v, pool) for k, v in (
        ("t_start_s", res.t_start), ("doppler_hz", res.doppler_hz), ("code_phase_chips", res.code_phase_chips),
        ("amplitude", res.amp), ("mode", res.mode), ("doppler_err_hz", d_err), ("code_err_chips", c_err),
        ("nav_t_s", res.nav_t), ("nav_pos_e", res.nav_pos_e), ("nav_vel_e", res.nav_vel_e),
        ("nav_clk", res.nav_clk), ("nav_sigma_doppler_hz", res.nav_sigma_doppler_hz))}
    if getattr(res, "bit_source", None) is not None:
        arrays["bit_source"] = Deflated(res.bit_source, pool, shuffle=False)
    return attrs, arrays


def write_results_h5(path, cfg, settings, raw, methods, runs, base_seed, consume=False, keep=(), packed=None):
    """``results.h5`` of the (run, method) results ``raw`` (docs/ultratight.md); ``settings``: the run's
    ``scenario_runner.run_settings``. ``packed``: entries already made by :func:`pack_result` (by key; the
    others are packed here). ``consume``: remove each entry from ``raw`` (and ``packed``) once it is in the
    file's image (the image and all the results are then never held at once) — but for the keys in
    ``keep``, which keep what ``scenario_runner.make_plots`` draws (times, PRNs, errors)."""
    packed = {} if packed is None else packed
    pool = None

    def build(f):
        nonlocal pool
        f.attrs["schema"] = SCHEMA
        f.attrs["version"] = __version__
        f.attrs["config_json"] = json.dumps(cfg, default=str)
        f.attrs["methods"] = ",".join(methods)
        f.attrs["runs"] = int(runs)
        f.attrs["seed"] = int(base_seed)
        f.attrs["run_settings_json"] = json.dumps(settings)
        missing = [key for key in raw if key not in packed]
        if missing:
            pool = deflate_pool()
            for key in missing:
                packed[key] = pack_result(*raw[key], pool)
        for r, m in list(raw):
            res, d_err, c_err = raw.pop((r, m)) if consume else raw[(r, m)]
            if consume and (r, m) in keep:
                raw[(r, m)] = (SimpleNamespace(t_start=res.t_start, prns=res.prns), d_err, c_err)
            attrs, arrays = packed.pop((r, m)) if consume else packed[(r, m)]
            del res
            g = f.create_group(f"run{r:03d}/{m}")
            g.attrs["seed"] = int(base_seed + r)
            for k, v in attrs.items():
                g.attrs[k] = v
            for k in list(arrays):
                (arrays.pop(k) if consume else arrays[k]).write(g, k)

    try:
        write_h5_atomic(path, build)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
