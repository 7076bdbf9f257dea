"""Guards every command applies to its inputs, outputs, resources and signals (docs/reliability.md).

* :func:`check_io` resolves and checks a command's input and output paths **before any work**:
  inputs exist and are readable regular files; an output may not be (or link to) an input or
  another output, may not be a directory, its parent directory must exist (unless the command
  creates it) and be writable, and its name must fit the file system's limits.
* :func:`tmp_name`, :func:`atomic_path`, :func:`write_bytes_atomic`, :func:`write_text_atomic`,
  :func:`h5_image`: atomic writers. Temporary files carry the process id and a random suffix
  (``.NAME.tmp-PID-RANDOM`` beside the target, so concurrent runs never share one) and are removed
  on every exit path; the target appears only complete (``os.replace``).
* :func:`describe_os_error` / :func:`output_error`: ``ENOSPC``, ``EROFS``, ``EACCES``, ``EFBIG`` ...
  as one line naming the path and the cause (:class:`ultratight.errors.OutputError`).
* :func:`install_signal_handlers`: SIGINT, SIGTERM and SIGHUP all raise :class:`Interrupted` (a
  ``KeyboardInterrupt``), so every cleanup path written for Ctrl-C also runs for ``kill`` and a
  closed terminal; SIGXFSZ is ignored so that a file-size limit ends in an ``EFBIG`` error instead
  of killing the process. Exit status ``128 + signal number`` (130, 143, 129).
* :func:`check_disk`, :func:`check_memory`: up-front resource estimates against free disk space,
  available memory and :data:`MEMORY_FRACTION`; refused with the estimate in the message.
* :func:`json_dumps`: strict JSON (non-finite numbers become ``null``) for every ``--json``.
"""

import errno
import io
import json
import math
import os
import re
import secrets
import shutil
import signal
import stat
import sys
from contextlib import contextmanager
from pathlib import Path

from ultratight.errors import ConfigError, InputFileError, OutputError

# The CLI imports this module first and installs its signal handlers before any command loads
# numpy, numba or h5py; so this module imports only the standard library at load time, and h5py
# and numpy inside the few functions that need them (h5_image, h5_atomic, json_clean).

# exit status of a run stopped by a signal: 128 + signal number (the shell's convention)
HANDLED_SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None),
                                    getattr(signal, "SIGHUP", None)) if s is not None)
# a run may plan to hold at most this fraction of the memory available when it starts
MEMORY_FRACTION = 0.8

_ERRNO_TEXT = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large (file-size limit reached)",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOENT: "no such file or directory",
    errno.ENOTDIR: "a path component is not a directory",
    errno.EISDIR: "is a directory",
    errno.ENAMETOOLONG: "file name too long",
    errno.EIO: "input/output error",
    errno.EMFILE: "too many open files",
    errno.ENOMEM: "out of memory",
    errno.EEXIST: "already exists",
    errno.EXDEV: "cross-device rename",
}
_H5_ERRNO = re.compile(r"errno\s*=\s*(\d+)")


def os_errno(exc):
    """The errno of an OSError, also when HDF5 only quotes it in the message (``errno = 28``)."""
    if getattr(exc, "errno", None):
        return exc.errno
    m = _H5_ERRNO.search(str(exc))
    return int(m.group(1)) if m else None


def describe_os_error(exc):
    """Short cause of an OSError (``no space left on device``, ...)."""
    code = os_errno(exc)
    if code in _ERRNO_TEXT:
        return _ERRNO_TEXT[code]
    if code is not None:
        return os.strerror(code).lower()
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]


def output_error(path, exc, action="cannot write"):
    """:class:`OutputError` ``"{action} {path}: {cause}"``."""
    return OutputError(f"{action} {path}: {describe_os_error(exc)}")


# ------------------------------------------------------------------------------------------
# temporary names and atomic writers
# ------------------------------------------------------------------------------------------
def tmp_name(path):
    """A temporary name beside ``path``, unique per process and call: ``.NAME.tmp-PID-RANDOM``."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def _unlink_quiet(p):
    try:
        os.unlink(p)
    except OSError:
        pass


class StagedFile:
    """A file written under a temporary name beside its target (:func:`tmp_name`) and renamed onto
    it by :meth:`commit` — or removed by :meth:`discard` — so that the target is either complete or
    untouched. The package's one temp-file-and-rename: :func:`atomic_path` and every streaming
    writer (IF files and sidecars, generator truth, HDF5 result streams, RINEX) use it."""

    def __init__(self, path):
        self.path = Path(path)
        self.tmp = tmp_name(self.path)

    def commit(self):
        """Rename the temporary file onto the target (atomic on one file system)."""
        os.replace(self.tmp, self.path)

    def discard(self):
        """Remove the temporary file, if any."""
        _unlink_quiet(self.tmp)


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success rename it onto ``path``, on any exception
    (also an interruption) remove it. OSError becomes :class:`OutputError` naming ``path``."""
    staged = StagedFile(path)
    try:
        yield staged.tmp
        staged.commit()
    except OutputError:
        staged.discard()
        raise
    except OSError as exc:
        staged.discard()
        if isinstance(exc, InputFileError):
            raise
        raise output_error(staged.path, exc) from None
    except BaseException:
        staged.discard()
        raise


def write_bytes_atomic(path, data):
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(path)


def write_text_atomic(path, text):
    return write_bytes_atomic(path, text.encode("utf-8"))


def h5_image(build):
    """Build an HDF5 file in memory (``build(h5py.File)``) and return its bytes.

    HDF5 writing straight to a file that hits a full disk can leave the library in a state that
    crashes the interpreter; building the image in memory and writing it with plain file I/O turns
    every disk error into an ordinary OSError (use for outputs of bounded size). The image is built
    in a ``BytesIO`` and returned as a view of its buffer (no copy: the peak memory is the image
    once, not twice as with the core driver's ``get_file_image``)."""
    import h5py             # lazy: see the note at the imports

    bio = io.BytesIO()
    with h5py.File(bio, "w") as f:
        build(f)
    return bio.getbuffer()


def write_h5_atomic(path, build):
    """:func:`h5_image` written atomically to ``path``."""
    return write_bytes_atomic(path, h5_image(build))


@contextmanager
def h5_atomic(path):
    """``with h5_atomic(path) as f:`` fill an HDF5 file built in memory (:func:`h5_image`); it is
    written atomically to ``path`` when the block ends without an exception."""
    import h5py             # lazy: see the note at the imports

    bio = io.BytesIO()
    with h5py.File(bio, "w") as f:
        yield f
    write_bytes_atomic(path, bio.getbuffer())


def savefig_atomic(fig, path, dpi=110, **kwargs):
    """``fig.savefig`` through :func:`atomic_path` (format from the target's suffix, PNG by default)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=dpi, **kwargs)
    return path


# ------------------------------------------------------------------------------------------
# path checks before any work
# ------------------------------------------------------------------------------------------
def _name_max(d):
    try:
        return os.pathconf(d, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        return 255


def _path_max(d):
    try:
        return os.pathconf(d, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        return 4096


def _existing_ancestor(p):
    q = Path(os.path.abspath(p))
    while not os.path.exists(q) and q.parent != q:
        q = q.parent
    return q


def check_input_file(path, what="input file"):
    """Refuse (InputFileError) a path that is missing, not a regular file, or unreadable."""
    p = Path(path)
    if str(path) == "":
        raise InputFileError(f"{what}: empty path")
    try:
        st = p.stat()
    except FileNotFoundError:
        raise InputFileError(f"{what} not found: {p}") from None
    except OSError as exc:
        raise InputFileError(f"{what} {p}: {describe_os_error(exc)}") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputFileError(f"{what} {p} is a directory, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise InputFileError(f"{what} {p} is not a regular file (a FIFO, socket or device)")
    if not os.access(p, os.R_OK):
        raise InputFileError(f"{what} {p}: permission denied (not readable)")
    return p


def read_text_input(path, what, kind="text file"):
    """The text of a UTF-8 input file (a byte-order mark dropped); InputFileError naming ``path``
    when it cannot be read or is not ``kind`` (invalid UTF-8, NUL bytes). ``what`` names the file
    in the read error (e.g. ``"IMU CSV"``)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: not a {kind} (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if "\x00" in text:
        raise InputFileError(f"{path}: not a {kind} (contains NUL bytes)")
    return text


def _same(a, b):
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_path_length(path, flag="--out"):
    """ConfigError when a path or one of its components exceeds the file system's limits."""
    s = str(path)
    anc = _existing_ancestor(os.path.dirname(os.path.abspath(s)) or ".")
    nmax, pmax = _name_max(anc), _path_max(anc)
    if len(os.fsencode(os.path.abspath(s))) >= pmax:
        raise ConfigError(f"{flag}: path too long ({len(os.fsencode(os.path.abspath(s)))} bytes, limit {pmax})")
    for part in Path(s).parts:
        if len(os.fsencode(part)) > nmax:
            raise ConfigError(f"{flag}: file name too long ({len(os.fsencode(part))} bytes, limit {nmax}): "
                              f"{part[:32]}...")


def check_output_path(path, flag="--out", create_parent=False):
    """Refuse an output path that cannot be written (one line naming ``flag``)."""
    s = str(path)
    if s == "" or s.endswith(("/", os.sep)) and not Path(s).is_dir():
        raise ConfigError(f"{flag}: not a file name: {s!r}")
    p = Path(s)
    if "\x00" in s:
        raise ConfigError(f"{flag}: the path contains a NUL character")
    check_path_length(s, flag)
    if p.is_dir():
        raise ConfigError(f"{flag} {p} is a directory; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    anc = _existing_ancestor(parent)
    if not parent.exists():
        if not create_parent:
            raise ConfigError(f"{flag}: directory {parent} does not exist")
        if not anc.is_dir():
            raise ConfigError(f"{flag}: {anc} is not a directory")
        if not os.access(anc, os.W_OK | os.X_OK):
            raise ConfigError(f"{flag}: directory {anc} is not writable (permission denied)")
        return p
    if not parent.is_dir():
        raise ConfigError(f"{flag}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag}: directory {parent} is not writable (permission denied)")
    try:
        st = os.statvfs(parent)
        if st.f_flag & getattr(os, "ST_RDONLY", 1):
            raise ConfigError(f"{flag}: directory {parent} is on a read-only file system")
    except (OSError, AttributeError):
        pass
    if p.exists() and not p.is_file():
        raise ConfigError(f"{flag} {p} exists and is not a regular file")
    return p


def check_io(inputs=(), outputs=(), create_parents=False, companions=()):
    """Check a command's paths before it starts (module doc). ``inputs``/``outputs``: iterables of
    ``(flag, path)``; ``None`` paths are skipped. Outputs may not equal an input or each other, nor a
    companion file the command reads when present (``companions``: a sidecar), even while it is absent."""
    ins = [(f, p) for f, p in inputs if p is not None]
    outs = [(f, p) for f, p in outputs if p is not None]
    for flag, p in outs:
        check_output_path(p, flag, create_parent=create_parents)
    for flag, p in outs:
        for iflag, ip in ins:
            if Path(ip).exists() and _same(p, ip):
                raise ConfigError(f"{flag} {p} is the input {iflag} {ip}; refusing to overwrite an input file")
    for flag, p in outs:
        for cflag, cp in companions:
            if cp is not None and os.path.realpath(p) == os.path.realpath(cp):
                raise ConfigError(f"{flag} {p} is the path of the {cflag}; refusing to write an output there")
    for i, (fa, pa) in enumerate(outs):
        for fb, pb in outs[i + 1:]:
            if _same(pa, pb):
                raise ConfigError(f"{fa} and {fb} name the same file {pa}")


# ------------------------------------------------------------------------------------------
# resources
# ------------------------------------------------------------------------------------------
def human_bytes(n):
    n = float(n)
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"


def available_memory():
    """Bytes of memory available to a new allocation (MemAvailable; sysconf fallback)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None


def free_disk(path):
    """Free bytes on the file system holding ``path`` (or its nearest existing ancestor)."""
    try:
        return shutil.disk_usage(_existing_ancestor(path)).free
    except OSError:
        return None


def check_disk(path, nbytes, what):
    """ConfigError when ``nbytes`` (estimate) exceed the free space where ``path`` will be written."""
    if not math.isfinite(nbytes):
        raise ConfigError(f"{what}: size estimate is not finite")
    free = free_disk(path)
    if free is not None and nbytes > free:
        raise ConfigError(f"{what} needs about {human_bytes(nbytes)} but only {human_bytes(free)} is free "
                          f"on the file system of {path}")


def check_file_size(nbytes, what):
    """ConfigError when one output file of ``nbytes`` (estimate) would exceed this process's file-size
    limit (``RLIMIT_FSIZE``): refused before any work, as HDF5 written straight to a file does not
    survive hitting the limit (see :func:`h5_image`)."""
    try:
        import resource
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):
        return
    if limit != resource.RLIM_INFINITY and nbytes > limit:
        raise ConfigError(f"{what}: file too large (file-size limit reached): about {human_bytes(nbytes)}, "
                          f"the limit is {human_bytes(limit)}")


def check_memory(nbytes, what):
    """ConfigError when a run plans to hold more than MEMORY_FRACTION of the available memory."""
    if not math.isfinite(nbytes):
        raise ConfigError(f"{what}: memory estimate is not finite")
    avail = available_memory()
    if avail is not None and nbytes > MEMORY_FRACTION * avail:
        raise ConfigError(f"{what} would hold about {human_bytes(nbytes)} in memory, more than "
                          f"{MEMORY_FRACTION:.0%} of the {human_bytes(avail)} available")


# ------------------------------------------------------------------------------------------
# signals
# ------------------------------------------------------------------------------------------
class Interrupted(KeyboardInterrupt):
    """A run stopped by SIGINT, SIGTERM or SIGHUP (a KeyboardInterrupt, so cleanup paths agree)."""

    def __init__(self, signum=signal.SIGINT):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def name(self):
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"

    @property
    def exit_code(self):
        return 128 + self.signum


# the signal received, kept after the handler raised: an exception raised while the interpreter runs
# a finaliser (a weakref callback, ``__del__``) is printed and dropped, so long loops also call
# :func:`check_interrupted` and the CLI calls it when a command returns
_pending_signal = None


def _unraisable_hook(unraisable):
    # Once a handled signal has arrived the run is ending: an Interrupted raised inside a finaliser
    # is recorded in _pending_signal and raised again by check_interrupted(), and the finalisers of
    # objects the signal cut short (half-built library objects, e.g. during numba compilation)
    # fail on their own. The interpreter's "Exception ignored in ..." reports of either would only
    # add tracebacks to the one-line message.
    if _pending_signal is not None or isinstance(unraisable.exc_value, Interrupted):
        return
    (_outer_unraisablehook or sys.__unraisablehook__)(unraisable)


_outer_unraisablehook = None       # the hook in place before install_signal_handlers


def interrupted_signal():
    """The handled signal this run received (a number), or None."""
    return _pending_signal


def check_interrupted():
    """Raise :class:`Interrupted` again if a handled signal arrived (see ``_pending_signal``)."""
    if _pending_signal is not None:
        raise Interrupted(_pending_signal)


def _handler(signum, frame):
    global _pending_signal
    _pending_signal = int(signum)
    # one interruption per run: later signals are ignored so that the cleanup can finish
    for s in HANDLED_SIGNALS:
        try:
            signal.signal(s, signal.SIG_IGN)
        except (OSError, ValueError):
            pass
    raise Interrupted(signum)


def install_signal_handlers():
    """SIGINT/SIGTERM/SIGHUP -> :class:`Interrupted`; SIGXFSZ ignored (writes fail with EFBIG).

    Returns the previous handlers, for :func:`restore_signal_handlers` (the CLI restores them when
    it returns, so an in-process caller keeps its own handling)."""
    global _pending_signal, _outer_unraisablehook
    _pending_signal = None
    if sys.unraisablehook is not _unraisable_hook:
        _outer_unraisablehook = sys.unraisablehook
    sys.unraisablehook = _unraisable_hook
    previous = {}
    for s in HANDLED_SIGNALS + ((signal.SIGXFSZ,) if hasattr(signal, "SIGXFSZ") else ()):
        try:
            old = signal.getsignal(s)
            if s in HANDLED_SIGNALS and old is signal.SIG_IGN and s != signal.SIGINT:
                continue           # e.g. nohup: keep ignoring SIGHUP
            signal.signal(s, _handler if s in HANDLED_SIGNALS else signal.SIG_IGN)
            previous[s] = old
        except (OSError, ValueError, TypeError):   # not the main thread
            pass
    return previous


def restore_signal_handlers(previous):
    if _pending_signal is None and _outer_unraisablehook is not None:
        # after an interrupted run the quiet hook stays for the interpreter's shutdown, whose
        # finalisers are the ones that would report; the next install starts clean
        sys.unraisablehook = _outer_unraisablehook
    for s, h in (previous or {}).items():
        try:
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        except (OSError, ValueError, TypeError):
            pass


# partial output a command left for an interrupted run (set by the command, reported by the CLI)
_partial = []


def note_partial(path):
    """Record that ``path`` holds a partial output (``complete=false``) if the run is interrupted."""
    _partial.append(str(path))


_complete = []


def note_complete(path):
    """Record that ``path`` was written complete before the run ended (reported if interrupted later)."""
    _complete.append(str(path))


def partial_outputs():
    """Noted partial outputs that actually exist."""
    return [p for p in _partial if os.path.isfile(p)]


def complete_outputs():
    """Noted complete outputs that actually exist."""
    return [p for p in _complete if os.path.isfile(p)]


def interruption_note():
    """What an interrupted run left, for the one-line message."""
    parts, done = partial_outputs(), complete_outputs()
    if parts:
        what = f"partial output (complete=false) written to {', '.join(parts)}"
    else:
        what = "no partial output written" if done else "no output written"
    if done:
        what += f"; complete outputs kept: {', '.join(done)}"
    return what


def reset_partial():
    _partial.clear()
    _complete.clear()


# ------------------------------------------------------------------------------------------
# strict JSON
# ------------------------------------------------------------------------------------------
def json_clean(o):
    """Replace non-finite floats by None, numpy scalars/arrays by Python values (recursively)."""
    import numpy as np      # lazy: see the note at the imports
    if isinstance(o, bool) or o is None or isinstance(o, str):
        return o
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, int):
        return o
    if isinstance(o, dict):
        return {str(k): json_clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_clean(v) for v in o]
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return json_clean(float(o))
    if isinstance(o, np.ndarray):
        return json_clean(o.tolist())
    if isinstance(o, Path):
        return str(o)
    return str(o)


def json_dumps(obj, **kw):
    """Strict JSON text of ``obj`` (see :func:`json_clean`); never emits NaN/Infinity."""
    return json.dumps(json_clean(obj), allow_nan=False, **kw)
