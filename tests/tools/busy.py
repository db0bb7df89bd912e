"""Other work beside kinfly, as on a laptop that is compiling or browsing during a flight: N
processes that each keep a core busy, at the same priority as everything else."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Iterator


@contextlib.contextmanager
def busy_cores(count: int) -> Iterator[list[subprocess.Popen]]:
    """COUNT busy loops (`sh -c 'while :; do :; done'`) while the block runs; killed after."""
    burners = [subprocess.Popen(["sh", "-c", "while :; do :; done"], start_new_session=True)
               for _ in range(count)]
    try:
        yield burners
    finally:
        for burner in burners:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(burner.pid, signal.SIGKILL)
            burner.wait()
