"""A serial port for the mavlink backend's tests that can be unplugged and plugged back: a
pseudo-terminal (a real tty: termios, baud rates, hang-up) whose far end is bridged to a UDP
peer, the stand-in autopilot. The tty's name is given to kinfly-fw through a fixed symlink,
--link, as udev names a USB serial adapter by its id; SIGUSR1 unplugs it (the far end closes:
kinfly-fw's reads fail, as when the adapter is pulled out, and the symlink goes), SIGUSR2 plugs
in a new one under the same symlink. SIGTERM ends it. Progress lines on stdout: "bridge:
plugged /dev/pts/N", "bridge: unplugged".

    serial_bridge.py --link PATH --udp HOST:PORT
"""
from __future__ import annotations

import argparse
import os
import select
import signal
import socket
import time
import tty
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--link", type=Path, required=True)
    parser.add_argument("--udp", required=True, help="the autopilot stand-in's HOST:PORT")
    args = parser.parse_args()
    host, port = args.udp.rsplit(":", 1)
    peer = (host, int(port))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))

    wanted = {"plugged": True, "stop": False}
    signal.signal(signal.SIGUSR1, lambda *_: wanted.update(plugged=False))
    signal.signal(signal.SIGUSR2, lambda *_: wanted.update(plugged=True))
    signal.signal(signal.SIGTERM, lambda *_: wanted.update(stop=True))

    master = -1

    def plug() -> int:
        fd, slave = os.openpty()
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)  # kinfly-fw opens it by the link; the master sees a hang-up until then
        staged = args.link.with_suffix(".new")
        staged.unlink(missing_ok=True)
        staged.symlink_to(name)
        staged.replace(args.link)
        print(f"bridge: plugged {name}", flush=True)
        return fd

    while not wanted["stop"]:
        if wanted["plugged"] and master < 0:
            master = plug()
        elif not wanted["plugged"] and master >= 0:
            os.close(master)
            master = -1
            args.link.unlink(missing_ok=True)
            print("bridge: unplugged", flush=True)
        ready, _, _ = select.select([sock] + ([master] if master >= 0 else []), [], [], 0.05)
        if sock in ready:
            data = sock.recv(65536)
            if master >= 0:
                os.write(master, data)
        if master >= 0 and master in ready:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: nobody has the tty open (yet, or any more)
                time.sleep(0.02)
                continue
            sock.sendto(data, peer)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
