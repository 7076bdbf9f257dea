"""One documented ``ultratight scenario`` run (a paper's Monte Carlo table), as an acceptance run of
``ultratight bench``.

    python benchmarks/acceptance_scenario.py SCENARIO [scenario options ...] [--json OUT.json]

Runs ``python -m ultratight.receiver.cli scenario SCENARIO [options] --out TMP --no-plots`` in a
subprocess, prints what it prints (the paper's tables with our figures, per seed and pooled:
docs/paper_afm.md, docs/integration-experiments.md, docs/airdata.md name the commands), and with
``--json`` copies the run's ``metrics.json`` (``NAME_metrics.json``) there.  The exit status is the command's.
"""

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    out = None
    if "--json" in argv:
        k = argv.index("--json")
        if k + 1 >= len(argv):
            print("acceptance_scenario: --json needs a path", file=sys.stderr)
            return 2
        out = argv[k + 1]
        del argv[k:k + 2]
    if not argv or argv[0].startswith("-"):
        print("acceptance_scenario: name a scenario, e.g. paper-afm-jump --runs 10 --seed 1", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "ultratight.receiver.cli", "scenario", *argv, "--out", tmp, "--no-plots"]
        print("command: ultratight scenario " + " ".join(argv), flush=True)
        rc = subprocess.run(cmd).returncode
        metrics = sorted(Path(tmp).glob("*metrics.json"))       # metrics.json or NAME_metrics.json
        if rc == 0 and out is not None:
            if not metrics:
                print("acceptance_scenario: the run wrote no metrics.json", file=sys.stderr)
                return 1
            shutil.copyfile(metrics[0], out)
    return rc


if __name__ == "__main__":
    sys.exit(main())
