"""Small job functions for the executor tests (importable by pool and Ray workers)."""

import json
import os
import time
from pathlib import Path


def write_square(staging: Path, value: int, log: str, sleep: float = 0.0) -> dict:
    """Append one line per attempt to ``log`` (counts executions), then write value**2."""
    with open(log, "a") as fh:
        fh.write(f"{value} {os.getpid()}\n")
    time.sleep(sleep)
    (staging / "result.json").write_text(json.dumps({"value": value, "square": value * value}))
    return {"square": value * value}


def fail_first_attempt(staging: Path, flag: str) -> dict:
    """Raise on the first attempt (flag file absent), succeed on the next."""
    if not os.path.exists(flag):
        Path(flag).write_text("failed once")
        raise RuntimeError("simulated worker failure")
    (staging / "ok").write_text("ok")
    return {}
