"""What the paper-highdyn result depends on: the readings of Zhao et al. 2014 §3's "measurement noise
parameters x20", the paper-literal RACKF beside the default one, one channel beside all, and the
lock monitor — each reading a Monte-Carlo campaign (``ultratight campaign``, same seeds for every
reading), summarised in one Markdown table per reading (docs/ultratight.md, "What the result depends on").

    python benchmarks/study_highdyn.py --runs 10 [--workers K] [--out study_out] [--only NAME,...]
                                       [--duration S] [--fs-hz F] [--cache] [--list]
    python benchmarks/study_highdyn.py --report [--out study_out] [--only NAME,...]

Each reading's runs land in ``OUT/NAME/`` (one HDF5 per run): an interrupted study continues where
it stopped when run again (the campaigns' ``--resume``). ``--cache``: each run's IF is generated once and read from
disk by every method (the campaigns' ``--cache``; ≈ 1 GB per 60 s run at 4 MHz) and a reading's IF
files are deleted when the reading is done (truth and IMU stay). ``--report`` rebuilds ``OUT/study.md`` from the
readings already in ``OUT`` (their ``campaign.json``) without running anything; readings run with
different settings (a shorter ``--duration``, say) are reported each with its own. ``OUT/study.md`` and ``OUT/study.json`` are
written at the end (and after each reading), with the command line, the machine and the wall time.
"""

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

METHODS = ("pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf", "dlb-rackf-paper")
BURST = (5.0, 10.0)
FACTORS = (2.0, 3.0, 4.47, 10.0, 20.0)          # std factors; 4.47 = variance x 20
COAST = {"engine.lock_monitor": True, "engine.monitor_gates_tight": True}   # `--monitor coast`


def _burst(factor, place):
    return [{"t0_s": BURST[0], "t1_s": BURST[1], "noise_factor": factor, "place": place}]


def readings():
    """name -> (description, scenario overrides)."""
    out = {}
    for f in FACTORS:
        out[f"if-x{f:g}"] = (f"IF noise std x{f:g}", {"noise_events": _burst(f, "if")})
    for f in FACTORS:
        out[f"corr-x{f:g}"] = (f"correlator-output noise std x{f:g}", {"noise_events": _burst(f, "correlator")})
    for f in (4.47, 20.0):
        out[f"filter-r-x{f:g}"] = (f"filters' R x{f * f:g} (std x{f:g}), signal unchanged",
                                   {"noise_events": _burst(f, "filter-r")})
    out["if-x20-coast"] = ("IF noise std x20 (the default) with the lock monitor (coast / restart)",
                           dict({"noise_events": _burst(20.0, "if")}, **COAST))
    out["corr-x4.47-coast"] = ("correlator-output noise std x4.47 with the lock monitor (coast / restart)",
                               dict({"noise_events": _burst(4.47, "correlator")}, **COAST))
    return out


def _fmt(v, nd):
    return "—" if v is None else f"{v:.{nd}f}"


def _closeness(methods_js, paper):
    """Mean |log10(ours / paper)| over the channel's Doppler RMS cells (a cell the paper marks diverged
    counts 1; segments a shorter cut does not reach are left out), and whether the paper's order RACKF < CKF < UKF < PB-KF holds in
    0-20 s (channel)."""
    errs = []
    for m, p in paper.items():
        ours = methods_js.get(m)
        if ours is None:
            continue
        for a, b in zip(ours["doppler_rms_hz_channel"], p["doppler_rms_hz"]):
            if a is None:                 # no epochs in that segment (a shorter cut): not compared
                continue
            if b is None or not a > 0:
                errs.append(1.0)
            else:
                errs.append(abs(math.log10(a / b)))
    order = [methods_js[m]["doppler_rms_hz_channel"][0] for m in ("dlb-rackf", "dlb-ckf", "dlb-ukf", "pb-kf-utc")
             if m in methods_js]
    ordered = len(order) == 4 and all(x is not None for x in order) and all(
        order[i] < order[i + 1] for i in range(3))
    return (sum(errs) / len(errs) if errs else None), ordered


def table(name, desc, js):
    s = js["summary"]
    meth = s["methods"]
    lines = [f"### `{name}`: {desc}", "",
             f"{s['runs']} runs of {s['duration_s']:g} s; RMS over all 13 channels and runs, then channel {s['channel']} "
             "(the paper's one-channel table); '—' = no epochs in that segment.", "",
             "| method | Doppler Hz 0–20 / 20–40 / 40–60 (all) | channel 0 | code chip (all) | burst window Doppler Hz "
             "(before) | channels lost (all runs) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for m, v in meth.items():
        dd = " / ".join(_fmt(x, 3) for x in v["doppler_rms_hz"])
        dc = " / ".join(_fmt(x, 3) for x in v["doppler_rms_hz_channel"])
        cc = " / ".join(_fmt(x, 4) for x in v["code_rms_chips"])
        ev = v.get("noise_events") or []
        evs = "; ".join(f"{_fmt(e['doppler_rms_hz'], 3)} ({_fmt(e['doppler_rms_hz_before'], 3)})" for e in ev) or "—"
        lines.append(f"| {m} | {dd} | {dc} | {cc} | {evs} | {v['lock_lost_channels']} |")
    dist, ordered = _closeness(meth, s["paper_table3"])
    lines += ["", f"Distance to the paper's Table 3 (mean |log10 ours/paper|, channel 0 Doppler): "
                  f"{_fmt(dist, 2)}; paper's order RACKF < CKF < UKF < PB-KF in 0–20 s: {'yes' if ordered else 'no'}.",
              ""]
    return "\n".join(lines), {"distance": dist, "ordered": ordered}


OVERVIEW_METHODS = ("dlb-rackf", "dlb-ckf", "dlb-ukf", "pb-kf-utc", "dlb-rackf-paper")


def overview(summary):
    """One line per reading: channel-0 Doppler RMS in 0–20 s and channels lost (all runs) per method, the
    distance to the paper's Table 3 and whether its 0–20 s order holds."""
    meths = [m for m in OVERVIEW_METHODS if any(m in v["methods"] for v in summary.values())]
    head = ("| reading | runs × s | " + " | ".join(f"{m} Hz (lost)" for m in meths)
            + " | distance | paper's order |")
    lines = ["### Overview", "",
             "Channel 0 (the paper's one-channel table) Doppler RMS in 0–20 s, Hz, and in brackets the channels "
             "that lost lock over all runs (of 13 per run).", "",
             head, "|" + " --- |" * (len(meths) + 4)]
    for n, v in summary.items():
        cells = []
        for m in meths:
            x = v["methods"].get(m)
            cells.append("—" if x is None else f"{_fmt(x['doppler_rms_hz_channel'][0], 3)} ({x['lock_lost_channels']})")
        lines.append(f"| `{n}` | {v['runs']} × {v['duration_s']:g} | " + " | ".join(cells)
                     + f" | {_fmt(v['distance'], 2)} | {'yes' if v['ordered'] else 'no'} |")
    return "\n".join(lines + [""])


def _entry(name, desc, ov, js, wall_s):
    txt, score = table(name, desc, js)
    s = js["summary"]
    return txt, {"description": desc, "overrides": ov, "wall_s": wall_s, **score, "runs": s["runs"],
                 "duration_s": s["duration_s"], "methods": s["methods"]}


def report(out, names, allr):
    """Rebuild OUT/study.md (and study.json) from the readings' campaign.json files."""
    md, summary = [], {}
    for n in names:
        f = out / n / "campaign.json"
        if not f.is_file():
            continue
        js = json.loads(f.read_text())
        txt, entry = _entry(n, allr[n][0], None, js, None)
        md.append(txt)
        summary[n] = entry
    if not summary:
        print(f"study_highdyn: no finished reading in {out}", file=sys.stderr)
        return 1
    text = overview(summary) + "\n" + "\n".join(md)
    (out / "study.md").write_text(text)
    (out / "study.json").write_text(json.dumps(summary, indent=1))
    print(text)
    return 0


def _drop_if_files(cache_dir):
    """Delete the IF files (and their metadata) of a finished reading's cache entries."""
    for done in Path(cache_dir).glob("*/done.json"):
        try:
            files = json.loads(done.read_text())["files"]
        except (OSError, ValueError, KeyError):
            continue
        for k in ("if", "meta"):
            if k in files:
                (done.parent / files[k]["name"]).unlink(missing_ok=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--out", default="study_out")
    ap.add_argument("--only", default=None, help="comma-separated reading names (default: all; --list)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--duration", type=float, default=None, help="cut the scenario (default: its 60 s)")
    ap.add_argument("--fs-hz", type=float, default=None, help="front-end sampling rate (default: the scenario's)")
    ap.add_argument("--cache", action="store_true",
                    help="generate each run's IF once onto disk (deleted after the reading) instead of per method")
    ap.add_argument("--list", action="store_true", help="list the readings and exit")
    ap.add_argument("--report", action="store_true", help="rebuild OUT/study.md from the finished readings, run nothing")
    a = ap.parse_args(argv)
    allr = readings()
    if a.list:
        for k, (d, _) in allr.items():
            print(f"{k:18s} {d}")
        return 0
    names = list(allr) if a.only is None else [x.strip() for x in a.only.split(",") if x.strip()]
    unknown = [n for n in names if n not in allr]
    if unknown:
        print(f"study_highdyn: unknown reading(s) {', '.join(unknown)}; --list shows them", file=sys.stderr)
        return 2
    out = Path(a.out)
    if a.report:
        return report(out, names, allr)
    from ultratight.receiver.cli.campaign import run_campaign, start_client
    out.mkdir(parents=True, exist_ok=True)
    client, cluster, where = start_client(a.workers)
    print(f"study_highdyn: {where}; dashboard {client.dashboard_link}", file=sys.stderr)
    header = (f"Command: `python benchmarks/study_highdyn.py {' '.join(argv if argv is not None else sys.argv[1:])}`; "
              f"machine: {platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}; {where}.\n\n")
    md = []
    summary = {}
    t0 = time.perf_counter()
    try:
        for n in names:
            desc, ov = allr[n]
            ov = dict(ov)
            if a.duration is not None:
                ov["duration_s"] = a.duration
            if a.fs_hz is not None:
                ov["frontend.fs_hz"] = a.fs_hz
            tr = time.perf_counter()
            r = run_campaign("paper-highdyn", runs=a.runs, methods=a.methods.split(","), seed=a.seed,
                             out_dir=out / n, resume=True, overrides=ov, client=client, progress=True,
                             cache=a.cache)
            if a.cache:
                _drop_if_files(out / n / "cache")
            txt, summary[n] = _entry(n, desc, ov, r["json"], time.perf_counter() - tr)
            md.append(txt)
            (out / "study.md").write_text(header + overview(summary) + "\n" + "\n".join(md)
                                          + f"\nWall time so far {time.perf_counter() - t0:.0f} s.\n")
            (out / "study.json").write_text(json.dumps(summary, indent=1))
            print(f"study_highdyn: {n} done ({time.perf_counter() - tr:.0f} s)", file=sys.stderr)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    print(header + (overview(summary) if summary else "") + "\n" + "\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
