"""Child processes a test starts are always reaped: stopped the way a user stops them, then killed if they
do not go within a grace period, whatever happened in the test."""

from __future__ import annotations

import signal
import subprocess
from contextlib import contextmanager


@contextmanager
def reaped(proc: subprocess.Popen, sig: int = signal.SIGINT, grace_s: float = 60.0):
    """Yield `proc`; on leaving, send `sig` (Ctrl-C by default), wait up to `grace_s`, then SIGKILL and wait.
    `proc.returncode` afterwards says how it ended (negative: killed by that signal). The grace is generous
    on purpose: on a loaded 2-core machine a fake tracker took over 10 s to go after Ctrl-C."""
    try:
        yield proc
    finally:
        if proc.poll() is None:
            try:
                proc.send_signal(sig)
                proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=30)
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
