"""The QEMU plugin that counts the aarch64 build's instructions for `make bench`
(tests/bench/qemu_count_in.c, built by `make qemu-plugin`), on programs whose counts are known:
functions of hand-written aarch64 instructions, called a known number of times, one with a loop
and a callee, one whose entry is also its loop's target."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "tests" / "bench"))
from qemu_count import count_in, count_in_plugin  # noqa: E402

pytestmark = pytest.mark.aarch64

AARCH64_DIR = Path(os.environ.get("KINFLY_AARCH64_DIR", REPO_ROOT / "build-aarch64"))
CALLS = 7

# A loop of three turns (sub, add v, cbnz), then a call: per call 14 instructions of its own
# (stp, mov, 3 * 3, bl, ldp, ret) and the callee's 3, of which 3 + 1 are vector ones. main's loop around
# the calls is not counted, nor what the C library runs before and after main.
WITH_LOOP_AND_CALLEE = (r"""
__asm__(".text\n.global counted\n.type counted, %function\ncounted:\n"
        "  stp x29, x30, [sp, #-16]!\n  mov x3, #3\n"
        "1:\n  sub x3, x3, #1\n  add v0.4s, v0.4s, v1.4s\n  cbnz x3, 1b\n"
        "  bl callee\n  ldp x29, x30, [sp], #16\n  ret\n.size counted, .-counted\n"
        ".global callee\n.type callee, %function\ncallee:\n"
        "  fmul v2.4s, v2.4s, v3.4s\n  nop\n  ret\n.size callee, .-callee\n");
void counted(long n);
""", 17, 4)
# Its entry is its loop's target: four turns of two, then the return; one call, not four.
ENTRY_IS_LOOP_TARGET = (r"""
__asm__(".text\n.global counted\n.type counted, %function\ncounted:\n"
        "  sub x0, x0, #1\n  cbnz x0, counted\n  ret\n.size counted, .-counted\n");
void counted(long n);
""", 9, 0)
MAIN = r"""
int main(void) {
    for (int i = 0; i < CALLS; ++i) counted(4);
    return 0;
}
"""


@pytest.mark.parametrize("program", [WITH_LOOP_AND_CALLEE, ENTRY_IS_LOOP_TARGET],
                         ids=["loop-and-callee", "entry-is-loop-target"])
def test_the_plugin_counts_each_call_of_a_function_exactly(
        program: tuple[str, int, int], tmp_path: Path) -> None:
    code, instructions_per_call, simd_per_call = program
    plugin = count_in_plugin(AARCH64_DIR / "qemu-plugin", fetch=False)
    if plugin is None:
        message = f"the plugin's header is not in {AARCH64_DIR / 'qemu-plugin'}: make qemu-plugin"
        if os.environ.get("CI"):
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    source = tmp_path / "counted.c"
    source.write_text(code + MAIN)
    binary = tmp_path / "counted"
    # Static: no sysroot needed to run it, and main and counted are in its symbol table.
    subprocess.run(["aarch64-linux-gnu-gcc", "-O1", "-static", f"-DCALLS={CALLS}", source,
                    "-o", binary], check=True, capture_output=True)
    counted = count_in([binary], tmp_path, "counted", "main", plugin, tmp_path / "count.log")
    assert counted.calls == CALLS
    assert counted.instructions == CALLS * instructions_per_call
    assert counted.simd_instructions == CALLS * simd_per_call
