"""Both ends of a plain UDP multicast link, run inside a network namespace by
tests/system/test_link_shape.py to measure what the shaped `lo` does (scripts/netns.py,
LinkShape). Prints one JSON object.

    link_probe.py loss --count N [--flows F]    N numbered datagrams, alternating over F flows
                                                (sockets and ports: drone->ground, ground->drone)
                                                -> per flow, which arrived
    link_probe.py mtu --payload B --count N     N datagrams of B bytes -> fragments made, arrived
    link_probe.py rate --seconds S [--flows F]  a saturating sender of 1400-byte datagrams
                                                -> per flow, packets and span received

The receiver never loses a datagram of its own: loss/mtu drain the socket after each batch far
smaller than its buffer, and each result carries the namespace's UDP RcvbufErrors, which the
tests require to be 0."""
from __future__ import annotations

import argparse
import json
import select
import socket
import struct
import sys
import threading
import time

GROUP = "239.255.76.67"
BASE_PORT = 7667
BATCH = 200  # datagrams sent between drains: ~200 KB of socket memory, the buffer holds 8 MB
RCVBUF_BYTES = 8 << 20
FENCE_TIMEOUT_S = 2.0  # a bound on a fence's arrival, not a wait: it arrives within microseconds
SEQ = struct.Struct("!I")
FENCE = 0xFFFFFFFF
SO_TIMESTAMPNS = 35  # Linux's (asm-generic/socket.h); Python 3.11's socket module lacks it
TIMESPEC = struct.Struct("@qq")


def receiver(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
    sock.bind(("", port))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                    struct.pack("4s4s", socket.inet_aton(GROUP), socket.inet_aton("0.0.0.0")))
    return sock


def snmp(section: str) -> dict[str, int]:
    """The namespace's /proc/net/snmp counters of SECTION (Ip, Udp)."""
    rows = [line.split() for line in open("/proc/net/snmp") if line.startswith(section + ":")]
    return {name: int(value) for name, value in zip(rows[0][1:], rows[1][1:])}


def drain(sock: socket.socket, into: list[int]) -> bool:
    """Reads what is queued; True once a fence came (everything sent before it has been through
    lo: the loopback delivers in order)."""
    fenced = False
    while True:
        try:
            data = sock.recv(65536, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return fenced
        seq = SEQ.unpack_from(data)[0]
        if seq == FENCE:
            fenced = True
        else:
            into.append(seq)


def fence(sender: socket.socket, sock: socket.socket, port: int, into: list[int]) -> int:
    """Sends fences until one arrives (the link may drop some); returns how many it took."""
    for tries in range(1, 1000):
        sender.sendto(SEQ.pack(FENCE), (GROUP, port))
        deadline = time.monotonic() + FENCE_TIMEOUT_S
        while time.monotonic() < deadline:
            if select.select([sock], [], [], deadline - time.monotonic())[0] and drain(sock, into):
                return tries
    raise RuntimeError("no fence arrived in 1000 tries")


def run_loss(count: int, flows: int, payload: int) -> dict:
    socks = [receiver(BASE_PORT + f) for f in range(flows)]
    senders = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(flows)]
    received: list[list[int]] = [[] for _ in range(flows)]
    padding = b"\0" * (payload - SEQ.size)
    for start in range(0, count, BATCH):
        for seq in range(start, min(start + BATCH, count)):
            f = seq % flows
            senders[f].sendto(SEQ.pack(seq) + padding, (GROUP, BASE_PORT + f))
        for f in range(flows):
            drain(socks[f], received[f])
    for f in range(flows):
        fence(senders[f], socks[f], BASE_PORT + f, received[f])
    return {"count": count, "flows": flows,
            "received": [sorted(r) for r in received],
            "rcvbuf_errors": snmp("Udp")["RcvbufErrors"]}


def run_mtu(payload: int, count: int) -> dict:
    sock = receiver(BASE_PORT)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    before = snmp("Ip")
    arrived: list[int] = []
    sizes: set[int] = set()
    for seq in range(count):
        sender.sendto(SEQ.pack(seq) + b"\0" * (payload - SEQ.size), (GROUP, BASE_PORT))
        data = sock.recv(65536)  # no loss on this link: every datagram comes
        arrived.append(SEQ.unpack_from(data)[0])
        sizes.add(len(data))
    after = snmp("Ip")
    return {"payload": payload, "count": count, "arrived": len(arrived), "sizes": sorted(sizes),
            "fragmented": after["FragOKs"] - before["FragOKs"],
            "fragments": after["FragCreates"] - before["FragCreates"],
            "reassembled": after["ReasmOKs"] - before["ReasmOKs"]}


def run_rate(seconds: float, flows: int, payload: int) -> dict:
    socks = [receiver(BASE_PORT + f) for f in range(flows)]
    arrivals: list[list[float]] = [[] for _ in range(flows)]
    stop = threading.Event()

    def receive(f: int) -> None:
        # The kernel's arrival stamps, not the thread's: a receiver that falls behind the
        # spinning sender would otherwise stretch the span and understate the rate.
        socks[f].setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        socks[f].settimeout(0.2)
        while not stop.is_set():
            try:
                _, ancillary, _, _ = socks[f].recvmsg(65536, 64)
            except socket.timeout:
                continue
            for level, kind, stamp in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    seconds, nanoseconds = TIMESPEC.unpack(stamp[:TIMESPEC.size])
                    arrivals[f].append(seconds + nanoseconds * 1e-9)

    threads = [threading.Thread(target=receive, args=(f,)) for f in range(flows)]
    for thread in threads:
        thread.start()
    senders = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(flows)]
    data = b"\0" * payload
    sent = [0] * flows
    end = time.monotonic() + seconds
    while time.monotonic() < end:  # saturating: the cap's full queue drops what is too much
        for f in range(flows):
            senders[f].sendto(data, (GROUP, BASE_PORT + f))
            sent[f] += 1
    # The queue empties within its length after the last send; the receivers then go idle.
    time.sleep(0.5)
    stop.set()
    for thread in threads:
        thread.join()
    return {"payload": payload, "seconds": seconds, "sent": sent,
            "received": [len(a) for a in arrivals],
            "first_s": [a[0] if a else None for a in arrivals],
            "last_s": [a[-1] if a else None for a in arrivals],
            "rcvbuf_errors": snmp("Udp")["RcvbufErrors"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    loss = sub.add_parser("loss")
    loss.add_argument("--count", type=int, required=True)
    loss.add_argument("--flows", type=int, default=1)
    loss.add_argument("--payload", type=int, default=64)
    mtu = sub.add_parser("mtu")
    mtu.add_argument("--payload", type=int, required=True)
    mtu.add_argument("--count", type=int, default=50)
    rate = sub.add_parser("rate")
    rate.add_argument("--seconds", type=float, default=2.0)
    rate.add_argument("--flows", type=int, default=1)
    rate.add_argument("--payload", type=int, default=1400)
    args = parser.parse_args()
    if args.what == "loss":
        result = run_loss(args.count, args.flows, args.payload)
    elif args.what == "mtu":
        result = run_mtu(args.payload, args.count)
    else:
        result = run_rate(args.seconds, args.flows, args.payload)
    json.dump(result, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
