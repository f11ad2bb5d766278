"""Run CMD so that its whole process group dies with PARENT_PID (docs/scaling.md, "No orphans").

The guard leads a new process group; it SIGKILLs the group on SIGTERM/SIGINT/SIGHUP and when its parent
dies (``PR_SET_PDEATHSIG``), and a forked watchdog does the same when the guard itself is SIGKILLed (Ray
kills a worker's direct children only).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys

__all__ = ["command"]

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel for ``sig`` when this process's parent dies (Linux); False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def kill_group(*_args) -> None:
    os.killpg(os.getpgrp(), signal.SIGKILL)


def watchdog(guard_pid: int) -> int:
    """Fork a process that SIGKILLs this group when ``guard_pid`` dies; its pid."""
    pid = os.fork()
    if pid:
        return pid
    try:  # the child: wait for the guard's death (or a signal), then end the group
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(sig, kill_group)
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != guard_pid:
            kill_group()
        while True:
            signal.pause()
    finally:
        os._exit(0)


ENTRY = "import sys; from pipeline.cluster.guard import main; sys.exit(main())"


def command(parent_pid: int, cmd: list[str]) -> list[str]:
    """Build the command line that runs ``cmd`` under the guard.

    Parameters
    ----------
    parent_pid : int
        The process whose death kills ``cmd``'s process group.
    cmd : list of str
        The command to run.

    Returns
    -------
    list of str
        ``python -c ENTRY PARENT_PID -- CMD...``.
    """
    return [sys.executable, "-c", ENTRY, str(parent_pid), "--", *cmd]


def main(argv: list[str] | None = None) -> int:
    """Run ``argv = [PARENT_PID, "--", CMD...]`` under the guard; its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 3 or argv[1] != "--":
        print(f"usage: python -c {ENTRY!r} PARENT_PID -- CMD ...", file=sys.stderr)
        return 2
    parent, cmd = int(argv[0]), argv[2:]
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, kill_group)
    set_parent_death_signal(signal.SIGTERM)
    if os.getppid() != parent:  # the parent died before prctl took effect
        kill_group()
    dog = watchdog(os.getpid())
    try:
        return subprocess.call(cmd)
    finally:
        os.kill(dog, signal.SIGKILL)
        os.waitpid(dog, 0)

