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
