"""How torch's OpenMP threads wait between operators, chosen before torch loads (libgomp reads it once, at load).

A VCDGS training step is ~8000 operators, hundreds of them parallel regions, plus the splat kernels, which run on the
same threads (render/splat/parallel.h). Measured on 2 cores (facecap, quick preset, a joint step on 2 threads; issue
36, docs/BENCHMARKS.md "Where the second core went"):

- one process alone: threads that spin ~30 us after each region (``GOMP_SPINCOUNT=3000``) 82 ms a step; passive
  threads (``OMP_WAIT_POLICY=PASSIVE``, this module's only setting before) 116-120 ms: every parallel operator then
  waits for a sleeping thread to wake;
- two training processes sharing the 2 cores: spinning 256 ms a step each, passive 146 ms: a spinning thread burns
  the time slice the other process needs.

So a process that has the cores to itself spins briefly, and processes that share them (the worker pools, or a start
on a machine where other processes are computing) wait passively. A user's own ``OMP_WAIT_POLICY`` or
``GOMP_SPINCOUNT`` wins. Only the speed depends on this: a seeded run gives the same numbers either way.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager

SPIN_COUNT = "3000"  # libgomp spins ~100 per us: ~30 us, long enough to span the gap between a step's operators
CHOSEN = "T2BS_OPENMP_WAIT"  # set when this module chose the policy (so a worker pool may choose again for its workers)


def cpu_ticks() -> tuple[int, int]:
    """The machine's CPU time so far, from /proc/stat: (all ticks, idle + iowait ticks)."""
    with open("/proc/stat") as f:
        ticks = [int(x) for x in f.readline().split()[1:9]]
    return sum(ticks), ticks[3] + ticks[4]


def cores_busy(seconds: float = 0.15) -> bool:
    """Whether other processes keep at least half a core busy right now: the machine's CPU time in /proc/stat over
    ``seconds`` while this process sleeps (False where there is no /proc/stat). A sample, not the load average: a
    process started right after another one finished would read that one's load for a minute after."""
    try:
        total0, idle0 = cpu_ticks()
        time.sleep(seconds)
        total1, idle1 = cpu_ticks()
    except (OSError, ValueError, IndexError):
        return False
    total = total1 - total0
    return total > 0 and (total - (idle1 - idle0)) / total * (os.cpu_count() or 1) >= 0.5


def choose_wait_policy(shared: bool | None = None) -> str | None:
    """Set the OpenMP wait policy in this process's environment (read by torch's libgomp when torch loads, and by
    every process started from here): ``shared`` True = passive (processes share the cores), False = a short spin,
    None = the choice this process inherited from a t2bs parent, else decide by ``cores_busy``. Returns the choice
    ("passive" / "spin"), or None when the user set their own."""
    env = os.environ
    if CHOSEN not in env and ("OMP_WAIT_POLICY" in env or "GOMP_SPINCOUNT" in env):
        return None
    if shared is None and CHOSEN in env:  # a worker keeps what the pool that started it chose
        return env[CHOSEN]
    passive = cores_busy() if shared is None else shared
    env.pop("OMP_WAIT_POLICY", None)
    env.pop("GOMP_SPINCOUNT", None)
    if passive:
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    else:
        env["GOMP_SPINCOUNT"] = SPIN_COUNT
    env[CHOSEN] = "passive" if passive else "spin"
    return env[CHOSEN]


@contextmanager
def shared_cores():
    """Processes started inside this block wait passively (``choose_wait_policy(shared=True)``): a worker pool's
    processes share the cores. This process's own policy is fixed already; its environment is restored after."""
    keys = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", CHOSEN)
    saved = {k: os.environ.get(k) for k in keys}
    choose_wait_policy(shared=True)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
