"""The spawned worker pool (:func:`clrecon.core.resources.spawned_pool`) after its parent is killed.

A ``ProcessPoolExecutor`` of spawned workers makes named POSIX semaphores (its queues' locks) and
registers them with Python's resource tracker, a process of its own that outlives a kill -9 of
the run: it unlinked them and printed "There appear to be 5 leaked semaphore objects to clean up
at shutdown" per pool as the terminal's last line. The workers now release them when they notice
their parent is gone, so the tracker has nothing left to complain about; and the semaphores a
worker made itself (a ``multiprocessing`` lock made without a context, as tqdm's write lock is:
a spawned worker's default start method is spawn, so it is named and registered too).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent("""
    import sys, time
    from clrecon.core import resources
    pool = resources.spawned_pool(2)
    futures = [pool.submit(time.sleep, 0.2) for _ in range(4)]  # both workers started and busy
    for f in futures:
        f.result()
    names = resources.pool_semaphore_names(pool)
    print(" ".join(names), flush=True)
    time.sleep(120)  # killed here, the pool open
""")


def _killed(script: str) -> tuple[str, str]:
    """``script`` run in a child Python, killed with SIGKILL once it has printed its first line:
    (that line, the child's stderr once the workers and the tracker have ended too)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=str(ROOT))
    try:
        line = proc.stdout.readline()
        os.kill(proc.pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)  # EOF once the workers and the tracker have ended too
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, (line, err)  # not ended on its own
    return line, err


def _left_in_shm(names) -> list:
    """Those of the named semaphores ``names`` still in /dev/shm (Linux keeps them as sem.<name>)."""
    shm = Path("/dev/shm")
    return [n for n in names if shm.is_dir() and (shm / f"sem.{n.lstrip('/')}").exists()]


def test_kill_9_leaves_no_leaked_semaphore_and_no_warning():
    line, err = _killed(CHILD)
    names = line.split()
    assert names, err
    assert "leaked semaphore" not in err and "resource_tracker" not in err, err
    assert _left_in_shm(names) == []  # the semaphores themselves are gone


OWN_LOCK = textwrap.dedent("""
    import time
    from clrecon.core import resources
    pool = resources.spawned_pool(1)
    # in the worker, what tqdm's first progress counter does: a lock of the default context, kept
    pool.submit(exec, "import builtins, multiprocessing; builtins.kept = multiprocessing.RLock()").result()
    print(pool.submit(eval, "__import__('builtins').kept._semlock.name").result(), flush=True)
    time.sleep(120)  # killed here, the pool open
""")


def test_kill_9_releases_a_semaphore_the_worker_made():
    """The worker's own named semaphore is unlinked and unregistered too: before, the tracker printed
    "There appear to be 1 leaked semaphore objects" (the flaky end of
    tests/pipeline/test_executors.py::test_a_killed_run_leaves_no_helper_behind, where the helper's
    plan made tqdm's lock)."""
    line, err = _killed(OWN_LOCK)
    name = line.strip()
    assert name.startswith("/"), (name, err)  # a named semaphore, not unlinked at birth
    assert "leaked semaphore" not in err and "resource_tracker" not in err, err
    assert _left_in_shm([name]) == []
