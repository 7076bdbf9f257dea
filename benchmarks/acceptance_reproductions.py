"""The slow reproductions of the test suite (``pytest -m slow``), run in one subprocess, with each
node's outcome and the figure lines it prints.

    python benchmarks/acceptance_reproductions.py [--quick] [--nodes ID,ID,...] [--tests DIR]
        [--json OUT.json]

The slow tests reproduce documented figures end to end (the static 60 s and vehicle-turns
acceptance runs, the 28 dB-Hz sensitivity run, the atmosphere and all-in-view runs, RTKLIB's
agreement, the paper-fads Monte Carlo, the prefilter Monte Carlo, the IF-level campaign, the
trajectory-file circle, the 2000-example fuzzing; docs/claims.md lists them).  The default
suite deselects them (``addopts`` in pyproject.toml) except those also marked ``ci``.  This
script runs ``python -m pytest -m slow`` (``--quick``: ``-m "slow and ci"``, the ones CI runs
too; ``--nodes``: the node ids given) with the tests' printed output kept per node, and prints

    PASSED   tests/test_x.py::test_y  (12.3 s)
        <the lines the test printed: its measured figures>

for every node, then the counts.  Exit status 0 when every selected node passed (or was skipped
for want of data), 1 otherwise.  The figures and the outcome per node go to ``--json``.
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

from _common import add_common_args, finish

ROOT = Path(__file__).resolve().parents[1]
CAPTURE_HEADER = re.compile(r"^-+ Captured \w+ -+$")   # pytest's section line inside <system-out>


def node_id(classname, name, root):
    """pytest node id of a JUnit test case: ``a.b.test_c`` + ``test_d`` -> ``a/b/test_c.py::test_d``
    (a class inside the module stays after the file: ``a/test_c.py::TestE::test_d``)."""
    parts = classname.split(".")
    for k in range(len(parts), 0, -1):
        path = "/".join(parts[:k]) + ".py"
        if (root / path).is_file():
            return "::".join([path] + parts[k:] + [name])
    return f"{classname}::{name}"


def parse_junit(xml_path, root):
    """``{node id: {"outcome", "time_s", "lines", "message"}}`` from a pytest JUnit XML file."""
    nodes = {}
    for case in ET.parse(xml_path).getroot().iter("testcase"):
        outcome, message = "passed", ""
        for tag in ("failure", "error", "skipped"):
            el = case.find(tag)
            if el is not None:
                outcome = {"failure": "failed", "error": "error", "skipped": "skipped"}[tag]
                message = (el.get("message") or "").strip().splitlines()[0:1]
                message = message[0] if message else ""
                break
        out = case.find("system-out")
        lines = [ln for ln in (out.text or "").splitlines()
                 if ln.strip() and not CAPTURE_HEADER.match(ln)] if out is not None else []
        nodes[node_id(case.get("classname", ""), case.get("name", ""), root)] = {
            "outcome": outcome, "time_s": round(float(case.get("time") or 0.0), 2),
            "lines": lines, "message": message}
    return nodes


def run(tests, marker, nodes):
    """Run pytest on ``tests`` (or the given node ids) with ``-m marker``; ``(nodes, returncode,
    wall s)``."""
    root = Path(tests).resolve().parent
    with tempfile.TemporaryDirectory() as tmp:
        xml = os.path.join(tmp, "junit.xml")
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", marker,
               f"--junitxml={xml}", "-o", "junit_logging=system-out", "-o", "junit_family=xunit2"]
        cmd += list(nodes) if nodes else [str(Path(tests).resolve())]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if not os.path.exists(xml):
            tail = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-1:] or ["(no output)"]
            raise SystemExit(f"acceptance_reproductions: pytest wrote no report ({tail[0]})")
        return parse_junit(xml, root), proc.returncode, wall


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--nodes", default=None, help="comma-separated node ids (default: every slow test)")
    ap.add_argument("--tests", default=str(ROOT / "tests"), help="tests folder (default: the checkout's tests/)")
    args = ap.parse_args(argv)
    if not Path(args.tests).is_dir():
        print(f"acceptance_reproductions: tests folder {args.tests} not found", file=sys.stderr)
        return 2
    marker = "slow and ci" if args.quick else "slow"
    wanted = [n.strip() for n in args.nodes.split(",") if n.strip()] if args.nodes else []
    nodes, rc, wall = run(args.tests, marker, wanted)
    for nid, r in nodes.items():
        print(f"{r['outcome'].upper():8s} {nid}  ({r['time_s']:.1f} s)"
              + (f"  {r['message']}" if r["message"] else ""))
        for line in r["lines"]:
            print(f"    {line}")
    counts = {k: sum(r["outcome"] == k for r in nodes.values()) for k in ("passed", "failed", "error", "skipped")}
    print(f"{len(nodes)} nodes (-m '{marker}'): " + ", ".join(f"{v} {k}" for k, v in counts.items())
          + f"; pytest exit {rc}; {wall:.0f} s wall")
    finish(args, {"marker": marker, "nodes": nodes, "counts": counts, "pytest_returncode": rc,
                  "wall_s": round(wall, 1)})
    return 0 if nodes and rc == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
