"""Instructions of the aarch64 build itself, counted under qemu-aarch64 by the TCG plugin
qemu_count_in.c (inside one function, callees included, as callgrind's --toggle-collect counts
natively), so that the two counts sit side by side.

Debian ships qemu-user with plugin support but no plugin and no plugin header. The header comes
from the source package of the very qemu-user installed (a plugin must match its QEMU's API),
downloaded by apt-get from the Debian archive once, with its signatures checked as apt checks
any package, and kept under the cache folder with the plugin built from it.
"""
from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

REPO_ROOT = Path(__file__).resolve().parents[2]
PLUGIN_SOURCE = Path(__file__).resolve().parent / "qemu_count_in.c"


@dataclass(frozen=True)
class Counted:
    calls: int                # times the function was entered
    instructions: int         # executed inside it, callees included
    simd_instructions: int    # of those, Advanced SIMD (NEON) ones


def _qemu_source_version() -> str:
    try:
        return subprocess.run(["dpkg-query", "-W", "-f", "${source:Version}", "qemu-user"],
                              check=True, capture_output=True, text=True).stdout.strip()
    except (FileNotFoundError, subprocess.CalledProcessError) as error:
        raise RuntimeError("qemu-user is not installed: scripts/install-deps.sh aarch64") \
            from error


def _plugin_header(version: str, cache: Path) -> Path:
    """The folder holding qemu-plugin.h of qemu's source package VERSION."""
    folder = cache / f"qemu-{version.replace(':', '_')}"
    if (folder / "qemu-plugin.h").is_file():
        return folder
    # The archive's source lines, from the one definition the sysroot and the image use.
    lines = subprocess.run(
        ["bash", "-c", f"source {REPO_ROOT}/scripts/aarch64-common.sh && "
                       "kinfly_debian_sources main"],
        check=True, capture_output=True, text=True).stdout.splitlines()
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        (work / "sources.list").write_text(
            "".join(re.sub(r"^deb ", "deb-src ", line) + "\n" for line in lines))
        for sub in ("lists/partial", "cache/archives/partial"):
            (work / sub).mkdir(parents=True)
        apt = ["apt-get", "-q", "-o", f"Dir::Etc::SourceList={work}/sources.list",
               "-o", "Dir::Etc::SourceParts=/dev/null", "-o", f"Dir::State::Lists={work}/lists",
               "-o", f"Dir::Cache={work}/cache", "-o", "Debug::NoLocking=1"]
        subprocess.run([*apt, "update"], check=True, capture_output=True)
        subprocess.run([*apt, "source", "--download-only", f"qemu={version}"], cwd=work,
                       check=True, capture_output=True)
        tarball = next(work.glob("qemu_*.orig.tar.*"))
        subprocess.run(["tar", "-xf", tarball, "-C", work, "--wildcards",
                        "*/include/qemu/qemu-plugin.h"], check=True, capture_output=True)
        header = next(work.glob("*/include/qemu/qemu-plugin.h"))
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(header, folder / "qemu-plugin.h")
    return folder


def count_in_plugin(cache: Path) -> Path:
    """libcount_in.so for the installed qemu-user, built when missing or older than its source."""
    version = _qemu_source_version()
    header = _plugin_header(version, cache)
    plugin = header / "libcount_in.so"
    if not plugin.is_file() or plugin.stat().st_mtime < PLUGIN_SOURCE.stat().st_mtime:
        subprocess.run(["cc", "-O2", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC",
                        f"-I{header}", PLUGIN_SOURCE, "-o", plugin], check=True)
    return plugin


def mangled_symbol(program: Path, pattern: str) -> str:
    """The one symbol of PROGRAM (aarch64) whose mangled name matches the regex PATTERN."""
    names = subprocess.run(["aarch64-linux-gnu-nm", program], check=True, capture_output=True,
                           text=True).stdout.split()
    found = sorted({name for name in names if re.fullmatch(pattern, name)})
    if len(found) != 1:
        raise RuntimeError(f"{program}: {len(found)} symbols match {pattern}: {found[:4]}")
    return found[0]


def count_in(command: Sequence[str | Path], sysroot: Path, enter: str, leave: str,
             plugin: Path, log: Path) -> Counted:
    """Runs the aarch64 COMMAND under qemu-aarch64 with SYSROOT's libraries, counting from each
    entry to the function ENTER until execution reaches LEAVE (its caller)."""
    subprocess.run(["qemu-aarch64", "-L", sysroot,
                    "-plugin", f"{plugin},enter={enter},leave={leave}",
                    "-d", "plugin", "-D", log, *command], check=True, capture_output=True)
    found = re.search(r"count_in: calls (\d+) instructions (\d+) simd (\d+)", log.read_text())
    if not found:
        raise RuntimeError(f"the plugin wrote no count to {log}")
    return Counted(*(int(group) for group in found.groups()))
