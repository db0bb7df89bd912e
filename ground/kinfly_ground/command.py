"""`kinfly-ground command`: a signed command to a drone's flight stack (docs/flight.md,
"Commands"): a flight_command_t inside a signed_t on KINFLY_<vid>_COMMAND, with the vehicle's
key, the same HMAC, window and replay rules as the ground's corrections. Multicast on Wi-Fi is
never retransmitted, so the same envelope goes out several times; the drone takes the first copy
and counts the rest as copies. A loss can still take every copy (a burst on the Wi-Fi, a socket
buffer full on a busy drone), so a command not answered within RESEND_PERIOD_S is sent again,
signed anew, until answered or the wait ends; the drone acts on each command_id once."""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from kinfly import flight_command_t

from ._native import Channel, FlightStatus, Receiver, Signer, channel_name

KINDS = {"arm": flight_command_t.ARM, "disarm": flight_command_t.DISARM,
         "takeoff": flight_command_t.TAKE_OFF, "hold": flight_command_t.HOLD,
         "goto": flight_command_t.GO_TO, "mission": flight_command_t.MISSION,
         "land": flight_command_t.LAND}
COPY_PERIOD_S = 0.02  # the copies of one command: apart, so one burst of loss does not take all
# The drone answers within a status period (0.1 s) of taking a command; five of them without an
# answer mean the command, or its answer, was lost.
RESEND_PERIOD_S = 0.5


class CommandError(Exception):
    """A command that cannot be sent as given; the message names what is wrong."""


def read_waypoints(path: Path) -> list[tuple[float, float, float]]:
    """A mission file: one waypoint a line, `x y z` in metres in the flight stack's world
    (z down: heights are negative), `#` starts a comment."""
    try:
        lines = path.read_text().splitlines()
    except OSError as error:
        raise CommandError(f"mission file {path}: {error.strerror}") from error
    waypoints = []
    for number, line in enumerate(lines, start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        try:
            x, y, z = (float(w) for w in words)
        except ValueError:
            raise CommandError(f"{path}:{number}: want three numbers x y z, got {line.strip()!r}")
        waypoints.append((x, y, z))
    if not 2 <= len(waypoints) <= flight_command_t.MAX_WAYPOINTS:
        raise CommandError(f"{path}: a mission needs 2 to {flight_command_t.MAX_WAYPOINTS} "
                           f"waypoints (got {len(waypoints)})")
    return waypoints


def build(vehicle: int, kind: str, command_id: int, *, height_m: float = 0.0,
          target: Sequence[float] = (0.0, 0.0, 0.0), yaw_rad: float | None = None,
          waypoints: Sequence[tuple[float, float, float]] = (),
          max_speed_m_s: float = 0.0) -> flight_command_t:
    """YAW_RAD: a go-to's heading (flight_command_t.yaw_rad); None keeps the drone's."""
    if kind not in KINDS:
        raise CommandError(f"unknown command {kind!r} (one of {', '.join(KINDS)})")
    m = flight_command_t()
    m.utime = time.time_ns() // 1000
    m.vehicle_id = vehicle
    m.command_id = command_id
    m.kind = KINDS[kind]
    m.height_m = float(height_m)
    m.target_world_m = [float(v) for v in target]
    m.has_yaw = yaw_rad is not None
    m.yaw_rad = float(yaw_rad) if yaw_rad is not None else 0.0
    m.max_speed_m_s = float(max_speed_m_s)
    m.waypoint_count = len(waypoints)
    m.waypoints_world_m = [[float(v) for v in w] for w in waypoints]
    return m


class AnswerWatch:
    """The drone's answer to one command: the first flight_status_t of the vehicle that names
    the command (decoded by the native Receiver, within bounds, as the station does)."""

    def __init__(self, lc, vehicle: int, command_id: int) -> None:
        self._lc = lc
        self._vehicle = vehicle
        self._command_id = command_id
        self._receiver = Receiver()
        self.answer: FlightStatus | None = None
        lc.subscribe(channel_name(Channel.FLIGHT, vehicle), self._on_message)

    def _on_message(self, channel: str, data: bytes) -> None:
        received = self._receiver.receive(channel, data)
        if received is None:
            return
        channel_kind, vehicle, status = received
        if (channel_kind is Channel.FLIGHT and vehicle == self._vehicle
                and status.command_id == self._command_id):
            self.answer = status

    def wait(self, timeout_s: float) -> FlightStatus | None:
        """The answer, once it arrives; None if none within TIMEOUT_S."""
        deadline = time.monotonic() + timeout_s
        while self.answer is None:
            remaining_ms = int((deadline - time.monotonic()) * 1000)
            if remaining_ms <= 0:
                break
            self._lc.handle_timeout(remaining_ms)
        return self.answer


def send(lc, signer: Signer, command: flight_command_t, copies: int) -> bytes:
    """Publishes COPIES of the signed command (one envelope: the drone takes the first);
    returns the envelope."""
    envelope = signer.sign(command.encode())
    channel = channel_name(Channel.COMMAND, command.vehicle_id)
    for copy in range(copies):
        if copy:
            time.sleep(COPY_PERIOD_S)
        lc.publish(channel, envelope)
    return envelope


def send_until_answered(lc, signer: Signer, command: flight_command_t, copies: int,
                        answers: AnswerWatch, wait_s: float,
                        on_sent: Callable[[int], None]) -> tuple[FlightStatus | None, int]:
    """Sends the command (COPIES of it), again every RESEND_PERIOD_S while unanswered, until
    the answer comes or WAIT_S ends; returns the answer (None: none) and how often it was sent
    (ON_SENT is told each time). Each round is signed anew: the drone's Verifier takes only
    sequence numbers above the last and signing times within its window, which a copy of the
    first envelope would leave."""
    deadline = time.monotonic() + wait_s
    sent = 0
    while True:
        send(lc, signer, command, copies)
        sent += 1
        on_sent(sent)
        left_s = deadline - time.monotonic()
        if left_s <= 0 or answers.wait(min(RESEND_PERIOD_S, left_s)) is not None:
            return answers.answer, sent
