"""Where one ultra-tight engine run spends its time: a ``perf`` profile with numba's functions named.

    python benchmarks/profile_engine.py [--method dlb-rackf] [--duration S] [--workdir DIR]
                                        [--top N] [--nonatomic] [--json OUT.json]

A diagnostic, not a timing benchmark (``ultratight bench`` does not run it). It needs Linux ``perf``
(Debian package ``linux-perf``) and says so when it is missing. Steps:

1. the paper-highdyn cut (20 s at 4 MHz, cached in ``--workdir`` like ``bench_ultratight.py``);
2. the method compiled in this process on a 0.3 s run, into a fresh numba cache (a temporary folder:
   functions loaded from an existing cache carry no names this script can read);
3. a symbol map ``/tmp/perf-PID.map`` written from the process's own dispatchers (the address of
   every compiled function in numba's execution engine), which ``perf`` reads to name JIT code;
4. ``perf record`` of the method on the cut on one thread, with 64 bytes of user stack per sample
   (the heap set up as in a scenario's worker process, ``workers.fix_mmap_threshold``);
5. the share of every function (self time), and for the samples inside numba's reference counting
   (``NRT_incref`` / ``NRT_decref``, tiny leaf functions that do not touch the stack) the function
   that called it: the return address is the word at the sampled stack pointer.

The figures of docs/ultratight.md "Where an engine's time goes" come from this script.
"""

import argparse
import bisect
import collections
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import add_common_args, finish

NRT = ("NRT_incref", "NRT_decref")


def _short(name):
    """A numba function's mangled name (``_ZN`` + length-prefixed parts) as ``module.function``."""
    if not name.startswith("_ZN"):
        return name
    parts, i = [], 3
    while i < len(name) and name[i].isdigit():
        j = i
        while name[j].isdigit():
            j += 1
        n = int(name[i:j])
        parts.append(name[j:j + n])
        i = j + n
    return ".".join(parts) or name


def write_symbol_map():
    """``/tmp/perf-PID.map`` for every function numba compiled in this process; the (start, size,
    name) rows."""
    import gc

    from numba.core.registry import CPUDispatcher, cpu_target

    engine = cpu_target.target_context.codegen()._engine
    syms = {}
    for obj in gc.get_objects():
        if not isinstance(obj, CPUDispatcher):
            continue
        for cres in obj.overloads.values():
            for fn in cres.library._final_module.functions:
                if fn.is_declaration:
                    continue
                addr = engine.get_function_address(fn.name)
                if addr:
                    syms[addr] = fn.name
    addrs = sorted(syms)
    rows = []
    for i, a in enumerate(addrs):
        nxt = addrs[i + 1] if i + 1 < len(addrs) else a + 4096
        rows.append((a, min(nxt - a, 1 << 22), syms[a]))
    with open(f"/tmp/perf-{os.getpid()}.map", "w") as f:
        for a, size, name in rows:
            f.write(f"{a:x} {size:x} {name}\n")
    return rows


def _callers(dump_text, rows):
    """Caller of each reference-counting sample in ``perf script -D`` output (module docstring)."""
    starts = [r[0] for r in rows]
    ranges = {name: (a, a + size) for a, size, name in rows if name in NRT}

    def name_of(addr):
        i = bisect.bisect_right(starts, addr) - 1
        if i >= 0 and addr < rows[i][0] + rows[i][1]:
            return _short(rows[i][2])
        return "(outside numba)"

    counts = collections.Counter()
    raw, ip, off = bytearray(), None, None

    def flush():
        if ip is None or off is None or len(raw) < off + 16:
            return
        for n, (a, b) in ranges.items():
            if a <= ip < b:
                counts[name_of(struct.unpack_from("<Q", raw, off + 8)[0])] += 1

    for line in dump_text.splitlines():
        if "raw event: size" in line:
            flush()
            raw, ip, off = bytearray(), None, None
        m = re.match(r"\.\s+[0-9a-f]{4}:\s+((?:[0-9a-f]{2} ?)+)", line)
        if m:
            raw += bytes(int(x, 16) for x in m.group(1).split())
        m = re.search(r"PERF_RECORD_SAMPLE\(IP, 0x\w+\): \d+/\d+: (0x[0-9a-f]+)", line)
        if m:
            ip = int(m.group(1), 16)
        m = re.search(r"ustack: size \d+, offset (0x[0-9a-f]+)", line)
        if m:
            off = int(m.group(1), 16)
    flush()
    return counts


def main():
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--method", default="dlb-rackf")
    ap.add_argument("--duration", type=float, default=None, help="signal seconds profiled (20; --quick 5)")
    ap.add_argument("--workdir", default=None, help="data cache (default: a temporary folder)")
    ap.add_argument("--top", type=int, default=15, help="functions listed")
    ap.add_argument("--nonatomic", action="store_true",
                    help="compile with numba's non-atomic reference counts (its measurement switch "
                         "nrtdynmod._disable_atomicity; unsafe with threads: the run is on one): what the "
                         "atomic counts cost, from the epochs' time of two runs with and without")
    a = ap.parse_args()
    perf = shutil.which("perf")
    if perf is None:
        print("profile_engine: no `perf` on this machine (Debian package linux-perf); nothing measured")
        finish(a, {"skipped": "perf not found"})
        return 0
    dur = a.duration or (5.0 if a.quick else 20.0)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["NUMBA_CACHE_DIR"] = str(Path(tmp) / "numba")     # before numba loads: step 2
        if a.nonatomic:
            from numba.core.runtime import nrtdynmod
            nrtdynmod._disable_atomicity = 1
        from ultratight.receiver.cli.scenario_config import load_scenario
        from ultratight.receiver.cli.scenario_runner import prepare_data, run_method
        from ultratight.receiver.cli.workers import fix_mmap_threshold
        from ultratight.receiver.deep.options import EngineOptions

        fix_mmap_threshold(streaming=True)        # the heap of a scenario's worker process

        cfg = load_scenario("paper-highdyn", {"duration_s": max(dur, 1.0)})
        paths, _ = prepare_data(cfg, 1, Path(a.workdir or tmp))
        opts = EngineOptions(threads=1)
        run_method(paths, cfg, a.method, 1, duration_s=0.3, options=opts)
        rows = write_symbol_map()
        data = Path(tmp) / "perf.data"
        rec = subprocess.Popen([perf, "record", "-F", "999", "--call-graph", "dwarf,64", "-o", str(data),
                                "-p", str(os.getpid())], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(1.0)                       # perf attached
        res, _ = run_method(paths, cfg, a.method, 1, duration_s=dur, options=opts)
        rec.send_signal(signal.SIGINT)
        rec.wait()
        report = subprocess.run([perf, "report", "-i", str(data), "--no-children", "--sort", "sym", "--stdio"],
                                capture_output=True, text=True).stdout
        dump = subprocess.run([perf, "script", "-i", str(data), "-D"], capture_output=True, text=True).stdout
        os.unlink(f"/tmp/perf-{os.getpid()}.map")
    shares = []
    for line in report.splitlines():
        m = re.match(r"\s+([\d.]+)%\s+\[[.k]\]\s+(\S+)", line)
        if m:
            shares.append((float(m.group(1)), _short(m.group(2))))
    callers = _callers(dump, rows)
    n_ref = sum(callers.values())
    epochs = float(res.info.get("timing_s", {}).get("epochs", float("nan")))
    how = " (non-atomic reference counts)" if a.nonatomic else ""
    print(f"{a.method}, {dur:g} s of paper-highdyn on one thread{how}: {res.runtime_s:.2f} s, epochs {epochs:.2f} s; "
          f"{len(rows)} functions named")
    for pct, name in shares[:a.top]:
        print(f"  {pct:5.1f} %  {name}")
    print(f"reference counting by caller ({n_ref} samples):")
    for name, k in callers.most_common(a.top):
        print(f"  {100.0 * k / max(n_ref, 1):5.1f} %  {name}")
    out = {"method": a.method, "duration_s": dur, "runtime_s": res.runtime_s, "epochs_s": epochs,
           "nonatomic": bool(a.nonatomic),
           "self_share_percent": {n: p for p, n in shares[:50]},
           "nrt_share_percent": sum(p for p, n in shares if n in NRT),
           "nrt_callers_percent": {n: 100.0 * k / max(n_ref, 1) for n, k in callers.most_common()}}
    finish(a, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
