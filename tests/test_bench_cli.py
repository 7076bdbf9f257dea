"""``ultratight bench``: which scripts run with which arguments (the default set, ``--acceptance``,
``--only``), on a folder of tiny stand-in scripts so that no real benchmark runs; and
``benchmarks/acceptance_reproductions.py`` on a tiny tests folder."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ultratight.receiver.cli.commands.bench import ACCEPTANCE

ROOT = Path(__file__).resolve().parents[1]

# a stand-in benchmark: prints one figure line naming itself and its arguments, writes them to --json
FAKE = """import json, sys
argv = sys.argv[1:]
print("figure of {name}: 1.25 " + json.dumps(argv))
if "--json" in argv:
    with open(argv[argv.index("--json") + 1], "w") as fh:
        json.dump({{"argv": argv}}, fh)
sys.exit({status})
"""


def _run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], capture_output=True,
                          text=True, cwd=cwd)


@pytest.fixture
def bench_dir(tmp_path):
    d = tmp_path / "benchmarks"
    d.mkdir()
    scripts = {"bench_alpha.py", "bench_beta.py"} | {spec[0] for spec in ACCEPTANCE.values()}
    for s in scripts:
        (d / s).write_text(FAKE.format(name=s, status=0))
    return d


def _report(path):
    return json.loads(Path(path).read_text())


def _bench_names(d):
    """The default set: every bench_*.py of the folder (some acceptance runs use one with other arguments)."""
    return sorted(p.stem[len("bench_"):] for p in d.glob("bench_*.py"))


def test_default_set_is_the_bench_scripts_only(bench_dir, tmp_path):
    out = tmp_path / "r.json"
    r = _run("bench", "--dir", str(bench_dir), "--json", str(out))
    assert r.returncode == 0, r.stderr
    rep = _report(out)
    assert list(rep["benchmarks"]) == _bench_names(bench_dir) and {"alpha", "beta"} <= set(rep["benchmarks"])
    assert not any(n in rep["benchmarks"] for n in ACCEPTANCE)
    alpha = rep["benchmarks"]["alpha"]
    assert alpha["results"]["argv"][0] == "--json" and "--quick" not in alpha["results"]["argv"]
    assert alpha["output"][0].startswith("figure of bench_alpha.py: 1.25")
    assert rep["acceptance"] is False


def test_acceptance_flag_adds_every_acceptance_run_with_its_documented_arguments(bench_dir, tmp_path):
    out, data = tmp_path / "r.json", tmp_path / "data"
    r = _run("bench", "--dir", str(bench_dir), "--acceptance", "--data", str(data), "--json", str(out))
    assert r.returncode == 0, r.stderr
    rep = _report(out)["benchmarks"]
    assert list(rep) == _bench_names(bench_dir) + list(ACCEPTANCE)
    assert rep["acceptance_acquisition_real"]["results"]["argv"][:2] == ["--real", "-v"]
    # the README's paper-highdyn command, its data under --data/<name>
    argv = rep["acceptance_ultratight"]["results"]["argv"]
    assert argv[:argv.index("--data")] == ["--seeds", "1,2,3,4,5", "--duration", "60", "--monitor", "off",
                                           "--frontend-gain", "fixed", "--format", "ci16", "--noise-tau", "inf"]
    assert argv[argv.index("--data") + 1] == str(data / "acceptance_ultratight")
    assert rep["acceptance_ultratight_agc"]["results"]["argv"][7:12] == ["agc", "--format", "ci8", "--noise-tau", "0"]
    assert rep["acceptance_prefilter"]["results"]["argv"][:2] == ["--seeds", "5"]
    assert rep["acceptance_bits"]["results"]["argv"][0] == "check"
    assert rep["acceptance_bits_sweep"]["results"]["argv"][:2] == ["sweep", "--data"]
    assert rep["acceptance_bits_sweep_lnav"]["results"]["argv"][:5] == ["sweep", "--nav-data", "lnav",
                                                                        "--strategies", "assisted"]
    assert rep["acceptance_reproductions"]["results"]["argv"][0] == "--json"
    # the papers' tables: the documented scenario commands
    assert rep["scenario_paper_afm_jump"]["results"]["argv"][:5] == ["paper-afm-jump", "--runs", "10", "--seed", "1"]
    assert rep["scenario_paper_fads"]["results"]["argv"][:3] == ["paper-fads", "--runs", "100"]
    assert rep["scenario_paper_static_iakf"]["results"]["argv"][5:7] == ["--methods", "akf0,akf,iakf,kf,kf-true-noise"]
    # the documented variants: the scenario with TOML keys changed
    assert rep["variant_robust_flight_lsq"]["results"]["argv"][:6] == ["paper-robust-flight", "--runs", "10", "--seed",
                                                                       "1", "--set"]
    assert 'fads.altitude_curve="envelope"' in rep["variant_fads_linear_envelope"]["results"]["argv"]
    argv = rep["variant_fads_curve_loglinear_envelope_20"]["results"]["argv"]
    assert argv[:5] == ["paper-fads", "--runs", "20", "--seed", "1"] and 'fads.altitude_shape="log-linear"' in argv
    # the study writes no JSON: its printed tables are the figures
    study = rep["study_highdyn"]
    assert study["results"] == {} and "--json" not in study["output"][0]
    assert "--runs\", \"10\"" in study["output"][0] and str(data / "study_highdyn") in study["output"][0]
    assert '"--duration", "20"' in rep["study_highdyn_20s"]["output"][0]
    # the acceptance scripts' printed lines are echoed on stderr, prefixed by the run's name
    assert "[acceptance_bits] figure of acceptance_bits.py" in r.stderr


def test_quick_acceptance_uses_the_short_arguments(bench_dir, tmp_path):
    out = tmp_path / "r.json"
    r = _run("bench", "--dir", str(bench_dir), "--acceptance", "--quick", "--json", str(out))
    assert r.returncode == 0, r.stderr
    rep = _report(out)["benchmarks"]
    assert rep["alpha"]["results"]["argv"][-1] == "--quick"
    assert rep["acceptance_ultratight"]["results"]["argv"][0] == "--quick"
    assert rep["acceptance_prefilter"]["results"]["argv"][:2] == ["--seeds", "1"]
    assert rep["acceptance_reproductions"]["results"]["argv"][0] == "--quick"
    assert '"--runs", "2"' in rep["study_highdyn"]["output"][0]


def test_only_selects_an_acceptance_run_without_the_flag(bench_dir, tmp_path):
    out = tmp_path / "r.json"
    r = _run("bench", "--dir", str(bench_dir), "--only", "acceptance_bits,beta", "--json", str(out))
    assert r.returncode == 0, r.stderr
    rep = _report(out)["benchmarks"]
    assert list(rep) == ["beta", "acceptance_bits"]
    assert rep["acceptance_bits"]["results"]["argv"][:2] == ["check", "--data"]


def test_failing_acceptance_script_gives_exit_1_and_unknown_names_exit_2(bench_dir, tmp_path):
    (bench_dir / "acceptance_atmosphere.py").write_text(
        "import sys\nprint('half a table')\nprint('bad scenario', file=sys.stderr)\nsys.exit(3)\n")
    out = tmp_path / "r.json"
    r = _run("bench", "--dir", str(bench_dir), "--only", "acceptance_atmosphere,alpha", "--json", str(out))
    assert r.returncode == 1
    rep = _report(out)["benchmarks"]
    assert rep["acceptance_atmosphere"]["returncode"] == 3
    assert rep["acceptance_atmosphere"]["error"] == "bad scenario"
    assert rep["acceptance_atmosphere"]["output"] == ["half a table"]
    assert "results" in rep["alpha"]
    r = _run("bench", "--dir", str(bench_dir), "--only", "acceptance_nothing", "--json", str(tmp_path / "x.json"))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "acceptance_nothing" in lines[0]
    assert "acceptance_reproductions" in lines[0] and not (tmp_path / "x.json").exists()
    data_file = tmp_path / "data.txt"
    data_file.write_text("keep")
    r = _run("bench", "--dir", str(bench_dir), "--acceptance", "--data", str(data_file), "--json",
             str(tmp_path / "y.json"))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "--data" in lines[0]
    assert data_file.read_text() == "keep" and not (tmp_path / "y.json").exists()


# a stand-in benchmark whose work is done by a child process: 0.3 s of CPU with 150 MB touched
CHILD_WORK = """import subprocess, sys
code = "import time\\nb = bytearray(150 * 2 ** 20)\\nt = time.process_time()\\nwhile time.process_time() - t < 0.3:\\n    pass"
subprocess.run([sys.executable, "-c", code], check=True)
print("child done")
"""


def test_report_counts_the_cpu_time_and_memory_of_the_processes_a_script_waits_for(bench_dir, tmp_path):
    (bench_dir / "bench_alpha.py").write_text(CHILD_WORK)
    out = tmp_path / "r.json"
    r = _run("bench", "--dir", str(bench_dir), "--only", "alpha,beta", "--json", str(out))
    assert r.returncode == 1, r.stderr                  # alpha writes no report: listed as failed, still measured
    rep = _report(out)["benchmarks"]
    assert rep["alpha"]["output"] == ["child done"] and rep["alpha"]["error"] == "no report written"
    assert rep["alpha"]["cpu_s"] >= 0.3 and rep["alpha"]["max_rss_mb"] >= 150.0
    assert 0.0 <= rep["beta"]["cpu_s"] < rep["alpha"]["cpu_s"] and rep["beta"]["max_rss_mb"] < 150.0
    line = [ln for ln in r.stderr.splitlines() if ln.startswith("[bench] alpha:")][0]
    assert f"{rep['alpha']['cpu_s']:.1f} s CPU, {rep['alpha']['max_rss_mb']:.0f} MB peak RSS)" in line


TESTS = '''import pytest


@pytest.mark.slow
def test_figure():
    print("position RMS 0.162 m")


@pytest.mark.slow
def test_wrong():
    print("position RMS 0.9 m")
    assert 0.9 <= 0.243


def test_not_slow():
    pass
'''


def test_reproductions_report_each_slow_node_and_its_printed_figures(tmp_path):
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_demo.py").write_text(TESTS)
    script = ROOT / "benchmarks" / "acceptance_reproductions.py"
    out = tmp_path / "r.json"
    r = subprocess.run([sys.executable, str(script), "--tests", str(tests), "--json", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 1, r.stdout + r.stderr          # one slow node failed
    rep = _report(out)
    assert set(rep["nodes"]) == {"tests/test_demo.py::test_figure", "tests/test_demo.py::test_wrong"}
    assert rep["nodes"]["tests/test_demo.py::test_figure"] == {
        "outcome": "passed", "time_s": rep["nodes"]["tests/test_demo.py::test_figure"]["time_s"],
        "lines": ["position RMS 0.162 m"], "message": ""}
    assert rep["nodes"]["tests/test_demo.py::test_wrong"]["outcome"] == "failed"
    assert rep["nodes"]["tests/test_demo.py::test_wrong"]["lines"] == ["position RMS 0.9 m"]
    assert rep["counts"] == {"passed": 1, "failed": 1, "error": 0, "skipped": 0}
    assert "PASSED   tests/test_demo.py::test_figure" in r.stdout and "    position RMS 0.162 m" in r.stdout
    r = subprocess.run([sys.executable, str(script), "--tests", str(tests),
                        "--nodes", "tests/test_demo.py::test_figure"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 nodes (-m 'slow'): 1 passed, 0 failed" in r.stdout


@pytest.mark.parametrize("item", ["filter.iakf_start", "=1", 'filter.iakf_start=full-window'])
def test_scenario_variant_with_a_bad_set_item_is_one_line_error(item):
    script = ROOT / "benchmarks" / "acceptance_scenario.py"
    r = subprocess.run([sys.executable, str(script), "paper-static-iakf", "--set", item], capture_output=True, text=True)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "--set" in lines[0] and r.stdout == ""
