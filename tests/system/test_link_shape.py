"""The Wi-Fi-like link (scripts/netns.py, LinkShape) does what it says, measured with plain UDP
multicast between sockets in the shaped namespace (tests/tools/link_probe.py): the loss it is
given, independent or in runs of the mean length given, on both directions alike; the MTU; the
bandwidth cap.

The loss figures are statistical: each is checked within 5 standard deviations of its estimator,
derived next to the check, so a correct link fails about once in 2 million runs, and a link off
by a fifth of its loss (1 % for 1.2 %) fails nearly always. The probe's own socket never drops
(RcvbufErrors is 0), so everything missing was lost on the link."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Callable

import pytest
from netns import LinkShape, link_counters, set_loss

from conftest import REPO_ROOT

PROBE = REPO_ROOT / "tests" / "tools" / "link_probe.py"
SIGMAS = 5.0
WifiNetns = Callable[[LinkShape], list[str]]


def probe(prefix: list[str], *args: object) -> dict:
    done = subprocess.run([*prefix, sys.executable, PROBE, *map(str, args)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def loss_runs(lost: list[bool]) -> list[int]:
    """Lengths of the runs of consecutive True."""
    runs, run = [], 0
    for is_lost in lost:
        if is_lost:
            run += 1
        elif run:
            runs.append(run)
            run = 0
    return runs + ([run] if run else [])


def measure_loss(prefix: list[str], count: int, flows: int) -> tuple[list[bool], list[float]]:
    """Which of COUNT datagrams (sent in turn over FLOWS sockets) were lost; each flow's loss."""
    result = probe(prefix, "loss", "--count", count, "--flows", flows)
    assert result["rcvbuf_errors"] == 0, "the probe's socket dropped: the figures would be wrong"
    arrived = set().union(*result["received"])
    per_flow = [1 - len(got) / len(range(f, count, flows)) for f, got in
                enumerate(result["received"])]
    return [seq not in arrived for seq in range(count)], per_flow


@pytest.mark.parametrize("loss", [0.01, 0.10])
def test_independent_loss_on_both_directions(wifi_netns: WifiNetns, loss: float) -> None:
    count = 20000
    prefix = wifi_netns(LinkShape(loss=loss))
    # Two flows on their own sockets and ports, as drone->ground and ground->drone.
    lost, per_flow = measure_loss(prefix, count, flows=2)

    # Bernoulli losses: the fraction of n has sigma sqrt(loss (1 - loss) / n) (1 %: 0.07 % of
    # all 20000, 10 %: 0.21 %), each flow sqrt(2) that.
    fraction = sum(lost) / count
    assert abs(fraction - loss) <= SIGMAS * math.sqrt(loss * (1 - loss) / count), fraction
    for flow_loss in per_flow:
        assert abs(flow_loss - loss) <= SIGMAS * math.sqrt(loss * (1 - loss) / (count / 2)), \
            per_flow
    # Independent losses come in geometric runs of mean 1/(1 - loss), variance loss/(1 - loss)^2,
    # about count*loss*(1 - loss) of them.
    runs = loss_runs(lost)
    expected_runs = count * loss * (1 - loss)
    run_sigma = math.sqrt(loss / (1 - loss) ** 2 / expected_runs)
    assert abs(sum(runs) / len(runs) - 1 / (1 - loss)) <= SIGMAS * run_sigma, runs


def test_bursty_loss_has_the_mean_run_and_the_average(wifi_netns: WifiNetns) -> None:
    shape = LinkShape(loss=0.05, loss_run_packets=5)
    count = 50000
    prefix = wifi_netns(shape)
    lost, per_flow = measure_loss(prefix, count, flows=2)
    runs = loss_runs(lost)

    q = 1 / shape.loss_run_packets
    p = shape.loss * q / (1 - shape.loss)
    # The average of a two-state chain's indicator has the Bernoulli variance times
    # (1 + rho) / (1 - rho), rho = 1 - p - q its correlation from one packet to the next
    # (here 0.79: 8.5 times the variance; sigma 0.28 % of 50000).
    rho = 1 - p - q
    loss_sigma = math.sqrt(shape.loss * (1 - shape.loss) / count * (1 + rho) / (1 - rho))
    fraction = sum(lost) / count
    assert abs(fraction - shape.loss) <= SIGMAS * loss_sigma, fraction
    # Runs are geometric, mean 1/q, variance (1 - q)/q^2, about count*loss*q of them (500:
    # sigma of the mean 0.2 packets).
    expected_runs = count * shape.loss * q
    run_sigma = math.sqrt((1 - q) / q**2 / expected_runs)
    mean_run = sum(runs) / len(runs)
    assert abs(mean_run - shape.loss_run_packets) <= SIGMAS * run_sigma, mean_run
    # A burst starts only where the kernel has collected a set element that an earlier burst
    # left dead (scripts/netns.py: two sets take turns); at this test's ~1000 bursts a second a
    # start both refuse would bias the loss low: they are counted, and must stay negligible.
    assert link_counters(prefix)["burst_refused"] <= 0.01 * len(runs)
    # One channel state for both directions: each flow sees the average loss too.
    for flow_loss in per_flow:
        assert abs(flow_loss - shape.loss) <= SIGMAS * loss_sigma * math.sqrt(2), per_flow


def test_mtu_fragments_above_1472_bytes_of_payload(wifi_netns: WifiNetns) -> None:
    prefix = wifi_netns(LinkShape(mtu_bytes=1500))
    count = 50
    # 1500 - 20 (IP header) - 8 (UDP header) = 1472 bytes fit one packet.
    whole = probe(prefix, "mtu", "--payload", 1472, "--count", count)
    assert (whole["arrived"], whole["sizes"], whole["fragmented"]) == (count, [1472], 0)
    split = probe(prefix, "mtu", "--payload", 1473, "--count", count)
    assert (split["arrived"], split["sizes"]) == (count, [1473])
    assert (split["fragmented"], split["fragments"], split["reassembled"]) == \
        (count, 2 * count, count)


def test_rate_cap_is_shared_by_all_traffic(wifi_netns: WifiNetns) -> None:
    shape = LinkShape(rate_kbit_s=5000)
    prefix = wifi_netns(shape)
    payload = 1400
    result = probe(prefix, "rate", "--seconds", 2, "--flows", 2, "--payload", payload)
    assert result["rcvbuf_errors"] == 0
    # The qdisc counts each packet with its IP, UDP and lo's 14-byte link header.
    wire_bits = (payload + 28 + 14) * 8
    offered_kbit_s = sum(result["sent"]) * wire_bits / result["seconds"] / 1e3
    assert offered_kbit_s > 2 * shape.rate_kbit_s, "the sender did not saturate the link"
    span_s = max(result["last_s"]) - min(result["first_s"])
    kbit_s = (sum(result["received"]) - 1) * wire_bits / span_s / 1e3
    # A token bucket is exact but for its burst (2 frames, 0.2 % of the 2 s) and the receiver's
    # timestamps (a late thread, a few ms: under 1 %); 5 % leaves room for a loaded machine.
    assert abs(kbit_s - shape.rate_kbit_s) <= 0.05 * shape.rate_kbit_s, kbit_s
    # Both flows went through the one cap: neither was starved.
    assert min(result["received"]) > 0.25 * sum(result["received"]), result["received"]


@pytest.mark.parametrize("fields, message", [
    ({"loss": 1.2}, "loss=1.2"),
    ({"loss": 0.05, "loss_run_packets": 1.02}, "loss_run_packets=1.02"),
    ({"mtu_bytes": 100}, "mtu_bytes=100"),
    ({"rate_kbit_s": 0}, "rate_kbit_s=0"),
    ({"rate_kbit_s": 5000, "queue_ms": 0}, "queue_ms=0"),
])
def test_shapes_out_of_range_are_refused_by_name(fields: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LinkShape(**fields)


def test_burst_rules_follow_the_stationary_loss() -> None:
    # q = 1/5 leaves the bad state; p = 0.05 * 0.2 / 0.95 enters it (in millionths).
    rules = LinkShape(loss=0.05, loss_run_packets=5).nft_ruleset()
    assert "mod 1000000 < 200000 delete @bad" in rules
    assert "mod 1000000 < 10526 meta mark set" in rules
    assert LinkShape().nft_ruleset() == "" and LinkShape().tc_command() == []


# Sends COUNT datagrams to each of two UDP ports on 127.0.0.1 in turn, draining both sockets as it
# goes (so no receive buffer overflows), and prints how many arrived at each.
TWO_PORTS = """
import json, socket, sys
count, ports = int(sys.argv[1]), [int(p) for p in sys.argv[2:]]
receivers = []
for port in ports:
    r = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    r.bind(("127.0.0.1", port))
    r.setblocking(False)
    receivers.append(r)
sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
got = [0] * len(ports)
def drain():
    for i, r in enumerate(receivers):
        while True:
            try:
                r.recv(2048)
            except BlockingIOError:
                break
            got[i] += 1
for _ in range(count):
    for port in ports:
        sender.sendto(b"x" * 100, ("127.0.0.1", port))
    drain()
drain()
print(json.dumps(got))
"""
LOSSY_PORT, WHOLE_PORT = 7668, 7667


def test_a_loss_on_ports_spares_the_rest_and_is_lifted(netns: list[str]) -> None:
    """set_loss with udp_ports: half of the datagrams to that port lost, none to another port;
    counted only for that port; and after set_loss(None) nothing is lost (scripts/sim.py's
    link loss, the drone's bus beside it untouched)."""
    count = 2000

    def send() -> list[int]:
        done = subprocess.run([*netns, sys.executable, "-c", TWO_PORTS, str(count),
                               str(LOSSY_PORT), str(WHOLE_PORT)],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    set_loss(netns, LinkShape(loss=0.5, udp_ports=(LOSSY_PORT,)))
    lossy, whole = send()
    sigma = math.sqrt(count * 0.5 * 0.5)
    assert abs(lossy - count * 0.5) < SIGMAS * sigma, lossy
    assert whole == count
    counts = link_counters(netns)
    assert counts["seen"] == count and counts["dropped"] == count - lossy, counts
    set_loss(netns, None)
    assert send() == [count, count]
