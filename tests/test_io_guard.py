"""Unit tests of ultratight.io_guard (paths, atomic writers, errno lines, JSON, signals)."""

import errno
import json
import os
import signal
import sys

import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError, OutputError
from ultratight import io_guard


def test_tmp_names_are_unique_and_hidden(tmp_path):
    names = {io_guard.tmp_name(tmp_path / "x.h5") for _ in range(50)}
    assert len(names) == 50
    for n in names:
        assert n.parent == tmp_path and n.name.startswith(".x.h5.tmp-") and str(os.getpid()) in n.name


def test_atomic_path_cleans_up_on_error_and_interrupt(tmp_path):
    target = tmp_path / "out.bin"
    for exc in (RuntimeError("x"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with io_guard.atomic_path(target) as tmp:
                tmp.write_bytes(b"partial")
                raise exc
    assert list(tmp_path.iterdir()) == []
    io_guard.write_text_atomic(target, "ok")
    assert target.read_text() == "ok" and list(tmp_path.iterdir()) == [target]


def test_atomic_path_maps_os_errors_to_one_line(tmp_path):
    with pytest.raises(OutputError, match="no space left on device"):
        with io_guard.atomic_path(tmp_path / "y"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_h5_image_round_trip(tmp_path):
    import h5py
    p = io_guard.write_h5_atomic(tmp_path / "r.h5", lambda f: f.create_dataset("a", data=np.arange(5)))
    with h5py.File(p, "r") as f:
        assert f["a"][()].tolist() == [0, 1, 2, 3, 4]


def test_describe_os_error_reads_hdf5_messages():
    exc = OSError("Unable to create file (file write failed: errno = 28, error message = 'x')")
    assert io_guard.describe_os_error(exc) == "no space left on device"
    assert io_guard.describe_os_error(OSError(errno.EROFS, "ro")) == "read-only file system"


def test_check_io_refuses_inputs_as_outputs_and_duplicates(tmp_path):
    src = tmp_path / "in.bin"
    src.write_bytes(b"abc")
    os.link(src, tmp_path / "hard.bin")
    os.symlink(src, tmp_path / "soft.bin")
    for alias in ("in.bin", "hard.bin", "soft.bin", "./in.bin"):
        with pytest.raises(ConfigError, match="refusing to overwrite"):
            io_guard.check_io([("IN", src)], [("--out", tmp_path / alias)])
    (tmp_path / "sub").mkdir()
    with pytest.raises(ConfigError, match="name the same file"):
        io_guard.check_io([], [("--out", tmp_path / "a"), ("--csv", tmp_path / "sub" / ".." / "a")])
    with pytest.raises(ConfigError, match="does not exist"):
        io_guard.check_io([], [("--out", tmp_path / "no" / "a")])
    with pytest.raises(ConfigError, match="is a directory"):
        io_guard.check_io([], [("--out", tmp_path)])
    with pytest.raises(ConfigError, match="too long"):
        io_guard.check_io([], [("--out", tmp_path / ("n" * 400))])
    io_guard.check_io([("IN", src)], [("--out", tmp_path / "new.h5")])


def test_check_input_file_names_the_problem(tmp_path):
    with pytest.raises(InputFileError, match="is a directory"):
        io_guard.check_input_file(tmp_path)
    with pytest.raises(InputFileError, match="not found"):
        io_guard.check_input_file(tmp_path / "missing")


def test_resource_checks_state_the_estimate(tmp_path):
    with pytest.raises(ConfigError, match="needs about"):
        io_guard.check_disk(tmp_path, 1e30, "this run")
    with pytest.raises(ConfigError, match="in memory"):
        io_guard.check_memory(1e30, "this run")
    io_guard.check_disk(tmp_path, 1, "this run")
    io_guard.check_memory(1, "this run")


def test_json_dumps_is_strict():
    text = io_guard.json_dumps({"a": float("nan"), "b": [np.float32("inf"), np.int64(3)], "c": np.array([1.5]),
                                "d": np.bool_(True)})
    assert json.loads(text) == {"a": None, "b": [None, 3], "c": [1.5], "d": True}
    assert "NaN" not in text and "Infinity" not in text


def test_signal_handlers_raise_interrupted_and_are_restored():
    previous = io_guard.install_signal_handlers()
    try:
        with pytest.raises(io_guard.Interrupted) as ei:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                pass
        assert ei.value.exit_code == 128 + signal.SIGTERM and ei.value.name == "SIGTERM"
        assert isinstance(ei.value, KeyboardInterrupt)
    finally:
        io_guard.restore_signal_handlers(previous)
    assert signal.getsignal(signal.SIGTERM) == previous.get(signal.SIGTERM, signal.SIG_DFL)


def test_a_signal_swallowed_by_a_finaliser_still_ends_the_run(tmp_path):
    """An exception raised by the signal handler while a finaliser runs is dropped by the
    interpreter: the pending signal is raised again at the next check (and when the command
    returns), so the run still ends as interrupted (exit 128 + N). Once interrupted, finaliser
    failures are not reported (no tracebacks beside the one-line message); otherwise they are."""
    import signal as _signal

    from ultratight import io_guard

    class Noisy:
        def __del__(self):
            _signal.raise_signal(_signal.SIGTERM)   # the handler raises inside __del__

    class Broken:                                   # a half-built object whose finaliser fails
        def __del__(self):
            raise AttributeError("no attribute '_ptr'")

    caller_hook = sys.unraisablehook
    previous = io_guard.install_signal_handlers()
    reported = []
    io_guard._outer_unraisablehook = reported.append   # what would be printed
    try:
        Broken()                                    # no signal yet: reported as usual
        assert len(reported) == 1 and isinstance(reported[0].exc_value, AttributeError)
        Noisy()                                     # the signal's exception is lost in __del__
        Broken()
        assert len(reported) == 1                   # neither is reported once interrupted
        with pytest.raises(io_guard.Interrupted) as exc:
            io_guard.check_interrupted()
        assert exc.value.exit_code == 128 + _signal.SIGTERM
    finally:
        io_guard.restore_signal_handlers(previous)
    assert sys.unraisablehook is io_guard._unraisable_hook   # kept for the interpreter's shutdown
    io_guard._outer_unraisablehook = caller_hook
    previous = io_guard.install_signal_handlers()   # a new run starts without the old signal
    try:
        io_guard.check_interrupted()
    finally:
        io_guard.restore_signal_handlers(previous)
    assert sys.unraisablehook is caller_hook        # the caller's hook is back


def test_an_interrupted_cleanup_that_fails_still_reports_the_interruption(monkeypatch, capsys):
    """A signal whose exception the interrupted code swallowed, followed by a different failure of
    that code (a half-built library object, a file closed mid-write): one line, exit 128 + N."""
    import signal as _signal

    from ultratight.receiver import cli
    from ultratight.receiver.cli.commands import ins

    def run(args):
        try:
            _signal.raise_signal(_signal.SIGTERM)
        except KeyboardInterrupt:
            pass                                  # e.g. caught inside a library
        raise RuntimeError("library object left in a bad state")

    monkeypatch.setattr(ins, "run", run)
    assert cli.main(["ins", "paper-highdyn"]) == 128 + _signal.SIGTERM
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["ultratight ins: interrupted by SIGTERM; no output written"]
    # without a signal the same failure is a bug and shows its traceback
    monkeypatch.setattr(ins, "run", lambda args: (_ for _ in ()).throw(RuntimeError("bug")))
    with pytest.raises(RuntimeError):
        cli.main(["ins", "paper-highdyn"])
