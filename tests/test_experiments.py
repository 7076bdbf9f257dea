"""The experiment registry behind ``ultratight scenario``."""

import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.cli import experiments
from ultratight.receiver.cli import main
from ultratight.config import check_known_keys


def test_default_experiment_is_the_if_double_loop():
    path, raw, module = experiments.resolve("paper-highdyn")
    assert "experiment" not in raw
    assert module.__name__.endswith("if_double_loop")
    assert "if-double-loop" in experiments.list_experiments()
    assert experiments.check_methods(module, None) == list(module.DEFAULT_METHODS)


def test_unknown_experiment_is_one_line(tmp_path, capsys):
    p = tmp_path / "x.toml"
    p.write_text('experiment = "no-such-thing"\n')
    assert main(["scenario", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown experiment 'no-such-thing'" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["../x", "", "a b"])
def test_experiment_names_are_checked(name):
    with pytest.raises(ConfigError):
        experiments.get(name)


def test_check_known_keys_suggests():
    check_known_keys({"rate_hz": 1}, ("rate_hz", "preset"), "[imu]")
    with pytest.raises(ConfigError, match=r"\[imu\]: unknown key 'rate_hs' \(did you mean 'rate_hz'\?\)"):
        check_known_keys({"rate_hs": 1}, ("rate_hz", "preset"), "[imu]")
    with pytest.raises(ConfigError, match="expected one of preset, rate_hz"):
        check_known_keys({"zzz": 1}, ("rate_hz", "preset"), "[imu]")
