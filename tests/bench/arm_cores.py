"""The Arm core estimates the benchmarks share (docs/firmware.md, "Measured"): instructions
counted inside one function, by `valgrind --tool=callgrind` on the native build or by a QEMU
plugin on the aarch64 build (qemu_count.py), turned into time on a Cortex-A72 (Raspberry Pi 4)
and a Cortex-A76 (Raspberry Pi 5) at their clocks and an assumed IPC. One definition, for the
odometry (bench_onboard.py) and the flight stack (bench_flight_cost.py).
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
# A Cortex-A76 (Raspberry Pi 5) decodes four a cycle with a deeper out-of-order window that hides
# more of those misses, and has a 2 MB L3 besides: assumed 1.2-1.8, not measured (no A76 here).
A76_HZ = 2.4e9
A76_IPC_RANGE = (1.2, 1.8)


def callgrind_instructions(command: Sequence[str | Path], toggle_collect: str,
                           out_file: Path) -> int:
    """Instructions executed inside the functions toggle_collect names (callgrind's
    --toggle-collect pattern), running command once under callgrind."""
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out_file}",
                    f"--toggle-collect={toggle_collect}", *command],
                   check=True, capture_output=True)
    text = Path(out_file).read_text(errors="replace")
    return int(re.search(r"^summary:\s+(\d+)", text, re.MULTILINE).group(1))


def core_seconds(instructions: float, hz: float,
                 ipc_range: tuple[float, float]) -> tuple[float, float]:
    """[s] (fastest, slowest) time for this many instructions on a core at HZ, over IPC_RANGE."""
    return instructions / (hz * ipc_range[1]), instructions / (hz * ipc_range[0])


def core_estimate(instructions: float, hz: float,
                  ipc_range: tuple[float, float]) -> dict[str, list[float]]:
    """Frames a second and milliseconds a frame at this many instructions a frame, slowest IPC
    first for the rate, fastest first for the time."""
    seconds = core_seconds(instructions, hz, ipc_range)
    return {"fps_estimate": [round(1 / s, 1) for s in reversed(seconds)],
            "ms_per_frame_estimate": [round(1e3 * s, 1) for s in seconds]}


def a72_seconds(instructions: float) -> tuple[float, float]:
    """[s] (fastest, slowest) A72 time for this many instructions, over A72_IPC_RANGE."""
    return core_seconds(instructions, A72_HZ, A72_IPC_RANGE)
