"""Instructions of the aarch64 build itself, counted under qemu-aarch64 by the TCG plugin
qemu_count_in.c (inside one function, callees included, as callgrind's --toggle-collect counts
natively), so that the two counts sit side by side.

Debian ships qemu-user with plugin support but no plugin and no plugin header. The header comes
from the source package of the very qemu-user installed (a plugin must match its QEMU's API),
downloaded by apt-get from the Debian archive, with its signatures checked as apt checks any
package, and kept with the plugin built from it:

    .venv/bin/python tests/bench/qemu_count.py CACHE_DIR    (make qemu-plugin: build-aarch64/)

prints the plugin's path, fetching and building what is missing.
"""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
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


def _run(command: Sequence[str | Path], what: str, **kwargs: object) -> str:
    """COMMAND's standard output; a failure names WHAT and says what the command said."""
    try:
        return subprocess.run([str(c) for c in command], check=True, capture_output=True,
                              text=True, **kwargs).stdout
    except FileNotFoundError as error:
        raise RuntimeError(f"{what}: {command[0]} is not installed "
                           "(scripts/install-deps.sh aarch64)") from error
    except subprocess.CalledProcessError as error:
        raise RuntimeError(f"{what} failed (exit {error.returncode}): "
                           f"{(error.stderr or error.stdout).strip()[-2000:]}") from error


def _qemu_source_version() -> str:
    return _run(["dpkg-query", "-W", "-f", "${source:Version}", "qemu-user"],
                "asking dpkg for qemu-user's source version").strip()


def _plugin_folder(cache: Path, version: str) -> Path:
    return cache / f"qemu-{version.replace(':', '_')}"


def _fetch_header(version: str, folder: Path) -> None:
    """qemu-plugin.h of qemu's source package VERSION into FOLDER."""
    # The archive's source lines, from the one definition the sysroot and the image use.
    lines = _run(["bash", "-c", 'source "$1" && kinfly_debian_sources main', "bash",
                  REPO_ROOT / "scripts" / "aarch64-common.sh"],
                 "listing the Debian archive's sources").splitlines()
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        (work / "sources.list").write_text(
            "".join(re.sub(r"^deb ", "deb-src ", line) + "\n" for line in lines))
        for sub in ("lists/partial", "cache/archives/partial"):
            (work / sub).mkdir(parents=True)
        apt = ["apt-get", "-q", "-o", f"Dir::Etc::SourceList={work}/sources.list",
               "-o", "Dir::Etc::SourceParts=/dev/null", "-o", f"Dir::State::Lists={work}/lists",
               "-o", f"Dir::Cache={work}/cache", "-o", "Debug::NoLocking=1"]
        _run([*apt, "update"], "apt-get update of the Debian archive's source indices")
        _run([*apt, "source", "--download-only", f"qemu={version}"],
             f"downloading the source package qemu={version}", cwd=work)
        tarball = next(work.glob("qemu_*.orig.tar.*"), None)
        if tarball is None:
            raise RuntimeError(f"qemu={version}: no upstream tarball in the source package")
        _run(["tar", "-xf", tarball, "-C", work, "--wildcards", "*/include/qemu/qemu-plugin.h"],
             f"extracting qemu-plugin.h from {tarball.name}")
        header = next(work.glob("*/include/qemu/qemu-plugin.h"))
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(header, folder / "qemu-plugin.h")


def count_in_plugin(cache: Path, fetch: bool = True) -> Path | None:
    """libcount_in.so for the installed qemu-user under CACHE, built when missing or older than
    its source; the header is fetched when missing and FETCH, else None is returned."""
    version = _qemu_source_version()
    folder = _plugin_folder(cache, version)
    if not (folder / "qemu-plugin.h").is_file():
        if not fetch:
            return None
        _fetch_header(version, folder)
    plugin = folder / "libcount_in.so"
    if not plugin.is_file() or plugin.stat().st_mtime < PLUGIN_SOURCE.stat().st_mtime:
        _run(["cc", "-O2", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC", f"-I{folder}",
              PLUGIN_SOURCE, "-o", plugin], f"building {plugin.name}")
    return plugin


def mangled_symbol(program: Path, pattern: str) -> str:
    """The one symbol of PROGRAM (aarch64) whose mangled name matches the regex PATTERN."""
    names = _run(["aarch64-linux-gnu-nm", program], f"listing {program}'s symbols").split()
    found = sorted({name for name in names if re.fullmatch(pattern, name)})
    if len(found) != 1:
        raise RuntimeError(f"{program}: {len(found)} symbols match {pattern}: {found[:4]}")
    return found[0]


def count_in(command: Sequence[str | Path], sysroot: Path, enter: str, leave: str,
             plugin: Path, log: Path) -> Counted:
    """Runs the aarch64 COMMAND under qemu-aarch64 with SYSROOT's libraries, counting from each
    entry to the function ENTER until execution reaches LEAVE (its caller)."""
    _run(["qemu-aarch64", "-L", sysroot, "-plugin", f"{plugin},enter={enter},leave={leave}",
          "-d", "plugin", "-D", log, *command], f"{Path(command[0]).name} under qemu-aarch64")
    found = re.search(r"count_in: calls (\d+) instructions (\d+) simd (\d+)", log.read_text())
    if not found:
        raise RuntimeError(f"the plugin wrote no count to {log}")
    return Counted(*(int(group) for group in found.groups()))


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    try:
        print(count_in_plugin(Path(sys.argv[1])))
    except RuntimeError as error:
        print(f"qemu_count: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
