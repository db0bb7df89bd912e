"""A private network namespace for the demo, tests and benchmarks that run LCM between
processes: only `lo`, up, with the multicast route LCM needs, so nothing leaves the machine and
parallel runs do not hear each other. Needs root (or passwordless sudo).

Given a LinkShape, `lo` is made to behave like a Wi-Fi link: its MTU, random or bursty packet
loss, and a bandwidth cap with a bounded queue. This kernel has no netem, so loss is an nftables
rule on lo's ingress hook and the cap is a tbf qdisc on lo. What was measured about how loopback
multicast passes them (docs/wire.md, "A Wi-Fi-like link"):
- each datagram a socket sends crosses lo's egress (the qdisc) once and its ingress hook once,
  per IP fragment, whatever the number of local receivers and whether IP_MULTICAST_LOOP is set:
  every receiver gets the copy that went through lo, so a drop at the hook loses it for all
  of them, and a fragment dropped loses its whole datagram (IP reassembly comes after the hook);
- there is one device and one hook for every sender, so drone->ground and ground->drone traffic
  see the same loss, and a burst of loss hits both directions, as a fade on one radio channel;
- the tbf cap is shared by everything leaving through lo (both directions, every socket) like
  air time; packets the full queue refuses are dropped at the sender's side silently (a UDP
  sendto still succeeds; the kernel counts them as SndbufErrors).

Run by hand for experiments: `python scripts/netns.py --loss 0.05 --loss-run 5 -- COMMAND`
(--help)."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence

# LCM's default multicast group (udpm://239.255.76.67:7667) lies in this range.
MULTICAST_ROUTE = "239.0.0.0/8"
# nftables table holding the loss model, and its counters (link_counters).
LINK_TABLE = "kinfly_link"
# Probabilities become `numgen random mod RANDOM_MODULUS < k`: a resolution of 1e-6.
RANDOM_MODULUS = 1_000_000
# Bytes the qdisc counts on lo beyond the IP packet (lo's Ethernet-sized header).
LO_HEADER_BYTES = 14
_counter = itertools.count()


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be created here (not root, no sudo, no `ip`)."""


@dataclasses.dataclass(frozen=True)
class LinkShape:
    """How `lo` in the namespace differs from a perfect loopback: a Wi-Fi-like link.

    Loss follows the Gilbert model when loss_run_packets > 1: a two-state chain (good: packets
    pass, bad: packets are lost) stepped once per packet. Leaving the bad state has probability
    q = 1 / loss_run_packets per packet, so runs of lost packets are geometric with mean
    loss_run_packets; entering it has probability p, and the long-run loss is the chain's
    stationary pi = p / (p + q), hence p = loss * q / (1 - loss). loss_run_packets = 1 means
    independent losses (whose runs then average 1 / (1 - loss) packets, as any independent loss
    does); values between 1 and that would make losses avoid each other and are refused."""

    mtu_bytes: int = 1500  # [bytes] of lo, 576..65536; 1500 as Wi-Fi and Ethernet
    loss: float = 0.0  # long-run fraction of packets (IP fragments) dropped, [0, 0.9]
    loss_run_packets: float = 1.0  # mean run of consecutive losses; 1: independent losses
    rate_kbit_s: float | None = None  # cap on all traffic through lo [kbit/s]; None: no cap
    queue_ms: float = 100.0  # [ms] the cap's queue holds before dropping; > 0
    # Loss only for UDP datagrams to these ports (a unicast link beside a lossless local bus,
    # scripts/sim.py); empty: every packet. The cap, if any, is for everything still.
    udp_ports: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not 576 <= self.mtu_bytes <= 65536:
            raise ValueError(f"LinkShape.mtu_bytes={self.mtu_bytes}: must be within 576..65536 "
                             "(IPv4's minimum reassembly size .. lo's default)")
        if not 0.0 <= self.loss <= 0.9:
            raise ValueError(f"LinkShape.loss={self.loss}: a fraction within 0..0.9")
        if 0.0 < self.loss < 1.0 / RANDOM_MODULUS:
            raise ValueError(f"LinkShape.loss={self.loss}: below the rule's resolution "
                             f"1/{RANDOM_MODULUS}")
        independent_run = 1.0 / (1.0 - self.loss)
        if self.loss_run_packets != 1.0 and not self.loss_run_packets >= independent_run:
            raise ValueError(
                f"LinkShape.loss_run_packets={self.loss_run_packets}: 1 (independent losses) or "
                f">= {independent_run:.4g} (1 / (1 - loss), the mean run of independent losses); "
                "shorter runs would make losses avoid each other")
        if self.rate_kbit_s is not None and not self.rate_kbit_s >= 64:
            raise ValueError(f"LinkShape.rate_kbit_s={self.rate_kbit_s}: None or >= 64")
        if not self.queue_ms > 0:
            raise ValueError(f"LinkShape.queue_ms={self.queue_ms}: must be > 0")
        if not all(0 < port < 65536 for port in self.udp_ports):
            raise ValueError(f"LinkShape.udp_ports={self.udp_ports}: ports within 1..65535")

    @property
    def bursty(self) -> bool:
        return self.loss > 0 and self.loss_run_packets > 1.0

    def label(self) -> str:
        """A short name for tables: `5% loss, runs of 5, 2000 kbit/s`."""
        parts = [f"{self.loss * 100:g}% loss" if self.loss else "no loss"]
        if self.bursty:
            parts.append(f"runs of {self.loss_run_packets:g}")
        if self.rate_kbit_s is not None:
            parts.append(f"{self.rate_kbit_s:g} kbit/s ({self.queue_ms:g} ms queue)")
        if self.mtu_bytes != 1500:
            parts.append(f"MTU {self.mtu_bytes}")
        if self.udp_ports:
            parts.append(f"to UDP ports {', '.join(map(str, self.udp_ports))}")
        return ", ".join(parts)

    def nft_ruleset(self) -> str:
        """The nftables ruleset (for `nft -f -` inside the namespace) of the loss model, with
        named counters: `seen` (every packet at lo's ingress), `dropped` (lost by the model) and
        `burst_refused` (see below). Empty without loss."""
        if self.loss == 0:
            return ""
        threshold = lambda probability: round(probability * RANDOM_MODULUS)  # noqa: E731
        if not self.bursty:
            rules = [f"numgen random mod {RANDOM_MODULUS} < {threshold(self.loss)} "
                     "counter name dropped drop"]
            state = ""
        else:
            q = 1.0 / self.loss_run_packets
            p = self.loss * q / (1.0 - self.loss)
            # The chain's state is whether `lo` is in one of the dynamic sets `bad`, `bad_again`.
            # The kernel deletes an element from the packet path by marking it dead; its garbage
            # collector removes it later, and until then re-adding the same key fails (measured:
            # a third of burst starts at 1000 runs a second with the default 1 s interval, and
            # still 0-4 % with 10 ms, idle or busy). A burst that cannot start in `bad` starts
            # in `bad_again`, whose element died a burst earlier; only a start that both refuse
            # is lost, counted in `burst_refused` (the mark only tags the packet between rules)
            # so that a test can tell that the model held.
            sets = ("bad", "bad_again")
            state = "".join(f"  set {name} {{ type ifname; flags dynamic,timeout; timeout 1h; "
                            "gc-interval 10ms; size 65535; }\n" for name in sets)
            rules = [rule for name in sets for rule in (
                f"iifname @{name} numgen random mod {RANDOM_MODULUS} < {threshold(q)} "
                f"delete @{name} {{ iifname }} accept",
                f"iifname @{name} counter name dropped drop")]
            rules.append(f"numgen random mod {RANDOM_MODULUS} < {threshold(p)} meta mark set 0x6b66")
            rules += [f"meta mark 0x6b66 add @{name} {{ iifname }} meta mark set 0 "
                      "counter name dropped drop" for name in sets]
            rules.append("meta mark 0x6b66 meta mark set 0 counter name burst_refused")
        # Every IP fragment but the first lacks the UDP header: the ports' datagrams are kept
        # below the MTU (the chunks are), so none is fragmented.
        match = (f"udp dport {{ {', '.join(map(str, self.udp_ports))} }} "
                 if self.udp_ports else "")
        body = "\n".join(f"    {match}{rule}" for rule in ["counter name seen", *rules])
        return (f"table netdev {LINK_TABLE} {{\n"
                "  counter seen {}\n  counter dropped {}\n  counter burst_refused {}\n"
                f"{state}"
                "  chain ingress {\n"
                "    type filter hook ingress device lo priority 0; policy accept;\n"
                f"{body}\n  }}\n}}\n")

    def tc_command(self) -> list[str]:
        """The `tc` arguments of the cap (a tbf qdisc at lo's root), or [] without one. The
        bucket holds two full frames: enough for any packet, and the link never runs more than
        two frames ahead of its rate."""
        if self.rate_kbit_s is None:
            return []
        burst_bytes = 2 * (self.mtu_bytes + LO_HEADER_BYTES)
        return ["qdisc", "add", "dev", "lo", "root", "tbf", "rate", f"{self.rate_kbit_s:g}kbit",
                "burst", str(burst_bytes), "latency", f"{self.queue_ms:g}ms"]


def system_tool(name: str) -> str:
    """The path of NAME: Debian installs ip, tc and nft in /usr/sbin, which is often not on a
    user's PATH."""
    found = shutil.which(name, path=os.pathsep.join(
        [os.environ.get("PATH", os.defpath), "/usr/sbin", "/sbin"]))
    if found is None:
        package = {"nft": "nftables", "ip": "iproute2", "tc": "iproute2"}[name]
        raise NetnsUnavailable(f"`{name}` ({package}) is not installed")
    return found


def _privileged() -> list[str]:
    if os.geteuid() == 0:
        return []
    if shutil.which("sudo") and subprocess.run(["sudo", "-n", "true"],
                                               capture_output=True).returncode == 0:
        return ["sudo", "-n"]
    raise NetnsUnavailable("creating a network namespace needs root or passwordless sudo")


def as_root(prefix: Sequence[str]) -> list[str]:
    """The prefix that runs a command in PREFIX's namespace (as network_namespace yields it)
    with root's rights, for nft and tc, whoever the caller."""
    end = list(prefix).index("exec") + 2  # [sudo...] ip netns exec NAME [setpriv ...]
    return list(prefix[:end])


def link_counters(prefix: Sequence[str]) -> dict[str, int]:
    """Packets counted by the loss model so far: seen, dropped, burst_refused (LinkShape.
    nft_ruleset); all 0 without loss."""
    listed = subprocess.run([*as_root(prefix), system_tool("nft"), "-j", "list", "table",
                             "netdev", LINK_TABLE], capture_output=True, text=True)
    counts = {"seen": 0, "dropped": 0, "burst_refused": 0}
    if listed.returncode != 0:  # no table: the shape has no loss
        return counts
    for item in json.loads(listed.stdout)["nftables"]:
        if "counter" in item:
            counts[item["counter"]["name"]] = item["counter"]["packets"]
    return counts


def set_loss(prefix: Sequence[str], shape: LinkShape | None) -> None:
    """Replaces the loss model of PREFIX's namespace (as network_namespace yields it) with
    SHAPE's, or removes it (None): a link that turns lossy in flight, and back."""
    root = as_root(prefix)
    subprocess.run([*root, system_tool("nft"), "delete", "table", "netdev", LINK_TABLE],
                   capture_output=True)  # none yet: nothing to delete
    if shape is not None and (ruleset := shape.nft_ruleset()):
        _run(root, [system_tool("nft"), "-f", "-"], stdin=ruleset)


def _run(root: Sequence[str], command: list[str], stdin: str | None = None) -> None:
    done = subprocess.run([*root, *command], input=stdin, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)}: {done.stderr.strip()}")


def _shape_link(root: list[str], shape: LinkShape) -> None:
    _run(root, [system_tool("ip"), "link", "set", "lo", "mtu", str(shape.mtu_bytes)])
    if ruleset := shape.nft_ruleset():
        _run(root, [system_tool("nft"), "-f", "-"], stdin=ruleset)
    if tc := shape.tc_command():
        _run(root, [system_tool("tc"), *tc])


@contextlib.contextmanager
def network_namespace(tag: str = "test", shape: LinkShape | None = None) -> Iterator[list[str]]:
    """Creates the namespace, shaped like SHAPE if given, and yields the command prefix that
    runs a program inside it; the namespace is deleted afterwards, whatever happened."""
    ip = system_tool("ip")
    if shape is not None:  # fail before creating anything
        if shape.loss:
            system_tool("nft")
        if shape.rate_kbit_s is not None:
            system_tool("tc")
    sudo = _privileged()
    name = f"kinfly-{tag}-{os.getpid()}-{next(_counter)}"
    created = subprocess.run([*sudo, ip, "netns", "add", name], capture_output=True, text=True)
    if created.returncode != 0:
        raise NetnsUnavailable(f"ip netns add {name}: {created.stderr.strip()}")
    try:
        root = [*sudo, ip, "netns", "exec", name]
        for command in (["link", "set", "lo", "up"],
                        ["route", "add", MULTICAST_ROUTE, "dev", "lo"]):
            subprocess.run([*root, ip, *command], check=True, capture_output=True)
        if shape is not None:
            _shape_link(root, shape)
        # Through sudo, the programs still run as the caller, at home: their files stay the
        # caller's (sudo's reset environment would give them root's HOME).
        as_caller = (["setpriv", f"--reuid={os.getuid()}", f"--regid={os.getgid()}",
                      "--init-groups", "env", f"HOME={os.path.expanduser('~')}"] if sudo else [])
        yield [*root, *as_caller]
    finally:
        subprocess.run([*sudo, ip, "netns", "del", name], capture_output=True)


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


def kill_group(process: subprocess.Popen) -> None:
    """SIGKILLs the process group of a program started with the namespace's prefix and
    `start_new_session=True`, as a crash ends it: sudo cannot pass SIGKILL on, so the whole
    session's group is killed."""
    sudo = _privileged()
    if not sudo:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        return
    subprocess.run([*sudo, "kill", "-KILL", "--", f"-{process.pid}"], capture_output=True)


def main() -> int:
    parser = argparse.ArgumentParser(
        description="Runs COMMAND (default: $SHELL) in a private network namespace whose lo is "
                    "shaped like a Wi-Fi link; prints the rules applied and, at the end, the "
                    "loss model's packet counters.",
        epilog="example: scripts/netns.py --loss 0.05 --loss-run 5 --rate-kbit 5000 -- "
               "build/bin/kinfly-link-bench ground --seconds 10")
    parser.add_argument("--mtu", type=int, default=LinkShape.mtu_bytes, help="bytes")
    parser.add_argument("--loss", type=float, default=0.0, help="fraction of packets lost")
    parser.add_argument("--loss-run", type=float, default=1.0,
                        help="mean run of consecutive losses in packets (1: independent)")
    parser.add_argument("--rate-kbit", type=float, default=None, help="bandwidth cap, kbit/s")
    parser.add_argument("--queue-ms", type=float, default=LinkShape.queue_ms,
                        help="the cap's queue, ms")
    parser.add_argument("command", nargs="*", help="what to run (after --)")
    args = parser.parse_args()
    try:
        shape = LinkShape(mtu_bytes=args.mtu, loss=args.loss, loss_run_packets=args.loss_run,
                          rate_kbit_s=args.rate_kbit, queue_ms=args.queue_ms)
    except ValueError as err:
        parser.error(str(err))
    print(f"[netns] {shape.label()}, MTU {shape.mtu_bytes}", file=sys.stderr)
    for line in (shape.nft_ruleset(), " ".join(["tc", *shape.tc_command()])):
        if line.strip() != "tc":
            print(line.rstrip(), file=sys.stderr)
    with network_namespace("shell", shape) as prefix:
        code = subprocess.run([*prefix, *(args.command or [os.environ.get("SHELL", "sh")])]
                              ).returncode
        print(f"[netns] counters: {json.dumps(link_counters(prefix))}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
