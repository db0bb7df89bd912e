"""The QEMU plugin that counts the aarch64 build's instructions for `make bench`
(tests/bench/qemu_count_in.c), on a program whose count is known: a function of hand-written
aarch64 instructions, called a known number of times. The plugin's header comes from Debian's
qemu source package (fetched once into build-aarch64/qemu-plugin/)."""
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
# counted: 5 scalar, 3 vector instructions and the return; main's loop around the calls is not
# counted, nor is what the C library runs before and after main.
PROGRAM = r"""
__asm__(".text\n.global counted\n.type counted, %function\ncounted:\n"
        "  add x1, x1, #1\n  add x1, x1, #2\n  mov x2, x1\n  nop\n  nop\n"
        "  add v0.4s, v0.4s, v1.4s\n  fmul v2.4s, v2.4s, v3.4s\n  ldr q4, [sp]\n"
        "  ret\n.size counted, .-counted\n");
void counted(void);
int main(void) {
    for (int i = 0; i < CALLS; ++i) counted();
    return 0;
}
"""
COUNTED_INSTRUCTIONS = 9
COUNTED_SIMD = 3


def test_the_plugin_counts_each_call_of_a_function_exactly(tmp_path: Path) -> None:
    source = tmp_path / "counted.c"
    source.write_text(PROGRAM)
    program = tmp_path / "counted"
    # Static: no sysroot needed to run it, and main and counted are in its symbol table.
    subprocess.run(["aarch64-linux-gnu-gcc", "-O1", "-static", f"-DCALLS={CALLS}", source,
                    "-o", program], check=True, capture_output=True)
    counted = count_in([program], tmp_path, "counted", "main",
                       count_in_plugin(AARCH64_DIR / "qemu-plugin"), tmp_path / "count.log")
    assert counted.calls == CALLS
    assert counted.instructions == CALLS * COUNTED_INSTRUCTIONS
    assert counted.simd_instructions == CALLS * COUNTED_SIMD
