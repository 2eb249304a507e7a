"""Loopback network helpers for the MAVLink tests: free ports and a lossy UDP proxy."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from collections.abc import Callable

import numpy as np

LOOPBACK = "127.0.0.1"


def free_udp_port(host: str = LOOPBACK) -> int:
    """A UDP port that was free a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class LossyUdpProxy:
    """A UDP relay on 127.0.0.1 that drops a share of the datagrams both ways.

    Ground stations send to :attr:`port` (``udpout:127.0.0.1:PORT``); the proxy
    forwards to ``target_port`` (a vehicle listening with ``udpin``) from its own
    socket and relays the answers back to the last ground-station address. Each
    direction draws its drops from its own stream of ``seed`` (``drop`` in [0, 1));
    setting :attr:`cut` drops everything from then on, :attr:`cut_after_up` = N does so
    once N more datagrams went up. ``drop_if(data, up)`` True drops that datagram too
    (a chosen loss, whatever the timing).
    """

    def __init__(self, target_port: int, drop: float = 0.0, seed: int = 0,
                 drop_if: Callable[[bytes, bool], bool] | None = None) -> None:
        self.target = (LOOPBACK, target_port)
        self.drop = drop
        self.drop_if = drop_if
        self.cut = False  # True: drop everything from now on (a link that dies)
        self.cut_after_up: int | None = None  # cut once this many more go up
        rng = np.random.default_rng(seed)
        self._rng_up, self._rng_down = (np.random.default_rng(s) for s in
                                        rng.bit_generator.seed_seq.spawn(2))
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind((LOOPBACK, 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind((LOOPBACK, 0))
        self.port = int(self.front.getsockname()[1])
        self._gcs: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lossy-proxy", daemon=True)
        self.passed = [0, 0]  # up (to the vehicle), down
        self.dropped = [0, 0]

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.05)
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65536)
                except OSError:
                    continue
                up = sock is self.front
                if up:
                    self._gcs = addr
                rng = self._rng_up if up else self._rng_down
                k = 0 if up else 1
                if self.cut or rng.random() < self.drop or (
                        self.drop_if is not None and self.drop_if(data, up)):
                    self.dropped[k] += 1
                    continue
                self.passed[k] += 1
                if up and self.cut_after_up is not None:
                    self.cut_after_up -= 1
                    if self.cut_after_up <= 0:
                        self.cut = True
                with contextlib.suppress(OSError):
                    if up:
                        self.back.sendto(data, self.target)
                    elif self._gcs is not None:
                        self.front.sendto(data, self._gcs)

    def __enter__(self) -> LossyUdpProxy:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.front.close()
        self.back.close()
