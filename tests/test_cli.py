"""CLI dispatcher behaviour: one-line errors and exit codes."""

import subprocess
import sys


def _run(*args):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], capture_output=True, text=True)


def test_version_and_help():
    r = _run("--version")
    assert r.returncode == 0 and "ultratight" in r.stdout
    r = _run("--help")
    assert r.returncode == 0 and "COMMAND" in r.stdout


def test_bench_unknown_name_is_one_line_error(tmp_path):
    r = _run("bench", "--only", "no-such-benchmark", "--json", str(tmp_path / "b.json"))
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "no-such-benchmark" in lines[0]
    assert not (tmp_path / "b.json").exists()


def test_quick_benchmarks_run(tmp_path):
    """The fast benchmarks in --quick mode run to the end against today's kernels (a benchmark that
    calls a kernel with an old signature fails here, not in a user's `ultratight bench`)."""
    import json
    out = tmp_path / "b.json"
    r = _run("bench", "--quick", "--only", "prefilter,correlator,sins,acquisition", "--json", str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads(out.read_text())["benchmarks"]
    assert set(rep) == {"prefilter", "correlator", "sins", "acquisition"}
    assert all(v["returncode"] == 0 for v in rep.values()), {k: v["returncode"] for k, v in rep.items()}
    assert rep["prefilter"]["results"]["rackf"]["kernel_us_per_epoch"] > 0
