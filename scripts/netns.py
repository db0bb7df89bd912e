"""A private network namespace for the demo, tests and benchmarks that run LCM between
processes: only `lo`, up, with the multicast route LCM needs, so nothing leaves the machine and
parallel runs do not hear each other. Needs root (or passwordless sudo)."""
from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import subprocess
from collections.abc import Iterator

# LCM's default multicast group (udpm://239.255.76.67:7667) lies in this range.
MULTICAST_ROUTE = "239.0.0.0/8"
_counter = itertools.count()


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be created here (not root, no sudo, no `ip`)."""


def _privileged() -> list[str]:
    if os.geteuid() == 0:
        return []
    if shutil.which("sudo") and subprocess.run(["sudo", "-n", "true"],
                                               capture_output=True).returncode == 0:
        return ["sudo", "-n"]
    raise NetnsUnavailable("creating a network namespace needs root or passwordless sudo")


@contextlib.contextmanager
def network_namespace(tag: str = "test") -> Iterator[list[str]]:
    """Creates the namespace and yields the command prefix that runs a program inside it; the
    namespace is deleted afterwards, whatever happened."""
    if shutil.which("ip") is None:
        raise NetnsUnavailable("`ip` (iproute2) is not installed")
    sudo = _privileged()
    name = f"kinfly-{tag}-{os.getpid()}-{next(_counter)}"
    created = subprocess.run([*sudo, "ip", "netns", "add", name], capture_output=True, text=True)
    if created.returncode != 0:
        raise NetnsUnavailable(f"ip netns add {name}: {created.stderr.strip()}")
    try:
        for command in (["ip", "link", "set", "lo", "up"],
                        ["ip", "route", "add", MULTICAST_ROUTE, "dev", "lo"]):
            subprocess.run([*sudo, "ip", "netns", "exec", name, *command], check=True,
                           capture_output=True)
        # Through sudo, the programs still run as the caller, at home: their files stay the
        # caller's (sudo's reset environment would give them root's HOME).
        as_caller = (["setpriv", f"--reuid={os.getuid()}", f"--regid={os.getgid()}",
                      "--init-groups", "env", f"HOME={os.path.expanduser('~')}"] if sudo else [])
        yield [*sudo, "ip", "netns", "exec", name, *as_caller]
    finally:
        subprocess.run([*sudo, "ip", "netns", "del", name], capture_output=True)


def send_signal(process: subprocess.Popen, sig: int) -> None:
    """Signals a program started with the namespace's prefix and `start_new_session=True`. Under
    sudo the process is sudo's, which the caller may not signal: `sudo kill` does, and sudo
    passes it on to the program (it would not, were the sender in the program's own session)."""
    sudo = _privileged()
    if not sudo:
        process.send_signal(sig)
        return
    subprocess.run([*sudo, "kill", f"-{signal.Signals(sig).name.removeprefix('SIG')}",
                    str(process.pid)], capture_output=True)
