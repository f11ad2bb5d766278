"""Run CMD so that its whole process group dies with PARENT_PID: :func:`command` is the command line
(``python -c`` calling :func:`main`; the library runs no module as a script).

A Ray task starts the guard as the leader of a new process group (``start_new_session``); the guard
starts CMD (``dvc repro``, which starts the stage's shell and Python) in that group.  Two ways the
group dies with the Ray worker:

* the worker crashes (SIGKILL, out of memory): the kernel sends the guard SIGTERM
  (``PR_SET_PDEATHSIG``, Linux) and the guard SIGKILLs its group;
* the worker exits because its raylet or driver is gone: Ray SIGKILLs the worker's direct children
  (``kill_child_processes_on_worker_exit``, not recursive), i.e. the guard itself, so the guard also
  forks a watchdog whose parent-death signal is SIGTERM and which SIGKILLs the group when the guard
  dies.

SIGTERM/SIGINT/SIGHUP to the guard (``ray.cancel``, ``scancel``) end the group too.  Without ``prctl``
(not Linux) only that last way works.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys

#: linux/prctl.h
PR_SET_PDEATHSIG = 1


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux); False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def kill_group(*_args) -> None:
    """SIGKILL this process's group: the guard, CMD and everything CMD started."""
    os.killpg(os.getpgrp(), signal.SIGKILL)


def watchdog(guard_pid: int) -> int:
    """Fork a process that SIGKILLs this process group when ``guard_pid`` (this process) dies; its pid."""
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


#: the guard's entry, run by :func:`command` as ``python -c``
ENTRY = "import sys; from pipeline.cluster.guard import main; sys.exit(main())"


def command(parent_pid: int, cmd: list[str]) -> list[str]:
    """The command line that runs ``cmd`` under the guard, its group dying with ``parent_pid``."""
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

