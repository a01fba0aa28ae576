"""flockcal's command line in a child process that reports its own peak resident memory (VmHWM from
/proc/self/status) as it exits. Not ru_maxrss: the kernel counts in it the pages of the fork that started
the child, which are the parent's (a test process of a few hundred MB would set the floor)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# What the installed `flockcal` script runs (`from flockcal.cli import main; sys.exit(main())`), reporting
# VmHWM to the file named first at exit.
RUN = ("import atexit, sys\n"
       "out = sys.argv.pop(1)\n"
       "def peak():\n"
       "    with open('/proc/self/status') as fh, open(out, 'w') as o:\n"
       "        o.write(next(l for l in fh if l.startswith('VmHWM:')).split()[1])\n"
       "atexit.register(peak)\n"
       "sys.argv[0] = 'flockcal'\n"
       "from flockcal.cli import main\n"
       "sys.exit(main())\n")


def run_flockcal(*argv, python: str = sys.executable, env: dict | None = None, cwd=None,
                 timeout: float = 3600) -> tuple[int, str, float, float]:
    """(exit status, stderr, peak resident bytes, seconds) of `flockcal ARGV` run by `python`."""
    fd, out = tempfile.mkstemp(prefix="flockcal-peak-")
    os.close(fd)
    started = time.monotonic()
    try:
        done = subprocess.run([python, "-c", RUN, out, *map(str, argv)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, env=dict(os.environ, **(env or {})), cwd=cwd,
                              timeout=timeout)
        text = Path(out).read_text()
    finally:
        os.unlink(out)
    return done.returncode, done.stderr, int(text) * 1024.0 if text else float("nan"), time.monotonic() - started
