"""``results.h5`` of ``ultratight scenario`` (docs/ultratight.md): per run and method the estimates, tracking
errors, arbitration modes and navigation solution, with the resolved configuration as attributes, written
atomically (:func:`ultratight.io_guard.write_h5_atomic`)."""

import json
from types import SimpleNamespace

import numpy as np

from ultratight import __version__
from ultratight.io_guard import write_h5_atomic

SCHEMA = "ultratight scenario results v1 (docs/ultratight.md)"


def write_results_h5(path, cfg, settings, raw, methods, runs, base_seed, consume=False, keep=()):
    """``results.h5`` of the (run, method) results ``raw`` (docs/ultratight.md); ``settings``: the run's
    ``scenario_runner.run_settings``. ``consume``: remove each entry from ``raw`` once it is in the file's
    image (the image and all the results are then never held at once) — but for the keys in ``keep``, which
    keep what ``scenario_runner.make_plots`` draws (times, PRNs, errors)."""

    def build(f):
        f.attrs["schema"] = SCHEMA
        f.attrs["version"] = __version__
        f.attrs["config_json"] = json.dumps(cfg, default=str)
        f.attrs["methods"] = ",".join(methods)
        f.attrs["runs"] = int(runs)
        f.attrs["seed"] = int(base_seed)
        f.attrs["run_settings_json"] = json.dumps(settings)
        for r, m in list(raw):
            res, d_err, c_err = raw.pop((r, m)) if consume else raw[(r, m)]
            if consume and (r, m) in keep:
                raw[(r, m)] = (SimpleNamespace(t_start=res.t_start, prns=res.prns), d_err, c_err)
            g = f.create_group(f"run{r:03d}/{m}")
            g.attrs["seed"] = int(base_seed + r)
            g.attrs["prn"] = np.asarray(res.prns, dtype=np.int64)
            g.attrs["runtime_s"] = float(res.runtime_s)
            g.attrs["info_json"] = json.dumps(res.info,
                                              default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
            for k, v in (("t_start_s", res.t_start), ("doppler_hz", res.doppler_hz),
                         ("code_phase_chips", res.code_phase_chips), ("amplitude", res.amp),
                         ("mode", res.mode), ("doppler_err_hz", d_err), ("code_err_chips", c_err),
                         ("nav_t_s", res.nav_t), ("nav_pos_e", res.nav_pos_e), ("nav_vel_e", res.nav_vel_e),
                         ("nav_clk", res.nav_clk), ("nav_sigma_doppler_hz", res.nav_sigma_doppler_hz)):
                g.create_dataset(k, data=np.asarray(v), compression="gzip", compression_opts=1, shuffle=True)
            if getattr(res, "bit_source", None) is not None:
                g.create_dataset("bit_source", data=np.asarray(res.bit_source), compression="gzip",
                                 compression_opts=1)

    write_h5_atomic(path, build)
