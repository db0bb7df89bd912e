"""What the station sends and hears: LCM, and the drones' unicast peers where there are some
(docs/wire.md, "Unicast on Wi-Fi"). What a peer sends is published on the local LCM, so the
station's subscriptions and an lcm-logger beside it hear it as they would multicast: one receive
path, whatever the transport."""
from __future__ import annotations

import select
from typing import Any

from ._native import PeerLink


class Transport:
    def __init__(self, lc: Any, peers: PeerLink | None = None) -> None:
        self._lc = lc
        self.peers = peers

    def publish(self, channel: str, data: bytes) -> None:
        # The peers first: LCM raises when this machine lost its multicast route.
        if self.peers is not None:
            self.peers.send(channel, data)
        self._lc.publish(channel, data)

    def handle(self, timeout_ms: int) -> None:
        """Handles what arrives within timeout_ms. OSError: a signal interrupted the wait."""
        if self.peers is None:
            self._lc.handle_timeout(timeout_ms)
            return
        lcm_fd, peer_fd = self._lc.fileno(), self.peers.fileno()
        readable, _, _ = select.select([lcm_fd, peer_fd], [], [], timeout_ms / 1000.0)
        if peer_fd in readable:
            for channel, data in self.peers.receive():
                self._lc.publish(channel, data)
        if lcm_fd in readable:
            self._lc.handle_timeout(0)
