"""The Cortex-A72 estimate the benchmarks share (docs/firmware.md, "Measured"): instructions
counted by `valgrind --tool=callgrind` inside one function on the native build (a proxy for the
aarch64 build: same source, same compiler), turned into A72 time at 1.5 GHz and an assumed IPC.
One definition, for the odometry (bench_onboard.py) and the flight stack (bench_flight_cost.py).
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Sequence

# A Cortex-A72 (Raspberry Pi 4) retires about one instruction per cycle on this kind of code:
# 3-wide decode, but gathers from the volume and the model maps miss its 1 MB L2 often. The flight
# stack's small matrices stay in L1, so for it the same range errs on the slow side.
A72_HZ = 1.5e9
A72_IPC_RANGE = (0.8, 1.2)


def callgrind_instructions(command: Sequence[str | Path], toggle_collect: str,
                           out_file: Path) -> int:
    """Instructions executed inside the functions toggle_collect names (callgrind's
    --toggle-collect pattern), running command once under callgrind."""
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out_file}",
                    f"--toggle-collect={toggle_collect}", *command],
                   check=True, capture_output=True)
    text = Path(out_file).read_text(errors="replace")
    return int(re.search(r"^summary:\s+(\d+)", text, re.MULTILINE).group(1))


def a72_seconds(instructions: float) -> tuple[float, float]:
    """[s] (fastest, slowest) A72 time for this many instructions, over A72_IPC_RANGE."""
    return (instructions / (A72_HZ * A72_IPC_RANGE[1]),
            instructions / (A72_HZ * A72_IPC_RANGE[0]))
