"""Whether a child process still runs, read from the system rather than from multiprocessing's own
records: when another part of the test process (an asyncio child watcher of an earlier in-process
run) reaps a child first, multiprocessing never learns its exit status and lists it as alive."""

from pathlib import Path


def still_running(p):
    """True while ``p`` (a multiprocessing Process) runs: not ended by its own records, and its pid
    neither gone nor a zombie in ``/proc``."""
    if p.exitcode is not None:
        return False
    stat = Path(f"/proc/{p.pid}/stat")
    try:
        text = stat.read_text()
    except OSError:                 # gone (or no /proc: trust multiprocessing)
        return not Path("/proc/self/stat").exists() and p.is_alive()
    return text[text.rindex(")") + 2] != "Z"


def running_since(before):
    """The processes started after ``before`` (a set of active children) that still run."""
    import multiprocessing
    return [p for p in set(multiprocessing.active_children()) - set(before) if still_running(p)]
