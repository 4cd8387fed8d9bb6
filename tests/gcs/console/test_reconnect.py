"""A console that loses its GCS says so, and reconnects when a GCS is back on the endpoint."""

from __future__ import annotations

import threading
import time

from gcs.console.client import ConsoleClient
from gcs.console.repl import Console
from gcs.ground_station import GroundStation
from gcs.operator.service import OperatorService
from protocol.link import Link, LinkConfig
from protocol.loopback import free_loopback_port, unique_mission

KEY = bytes(range(100, 132))


class _Gcs:
    """A GCS's operator side on ``endpoint``, its loop on a thread."""

    def __init__(self, endpoint: str, mission: str) -> None:
        self.link = Link(LinkConfig(listen=(endpoint,), pump_period_s=0.0), mission=mission)
        self.station = GroundStation()
        self.service = OperatorService(self.link, key=KEY, status_period_s=0.2)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        t = 0.0
        while not self.stop.wait(0.05):
            t += 0.05
            self.service.after_step(now_s=t, station=self.station, send=lambda r, m: None)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.service.close(self.station)
        self.link.close()


def _until(pred, timeout_s: float) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_console_notices_the_lost_gcs_and_reconnects() -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("console")
    gcs = _Gcs(endpoint, mission)
    notices: list[str] = []
    link = Link(LinkConfig(connect=(endpoint,), pump_period_s=0.0), mission=mission)
    client = ConsoleClient(link, "alice", KEY, silence_s=1.0, on_notice=notices.append)
    out: list[str] = []
    console = Console(client, out=out.append, reply_timeout_s=10.0, wait_s=20.0)
    try:
        assert client.wait_for_gcs(20.0)
        assert console.run_line("status") and out[-1].startswith("ok: t=")
        gcs.close()
        assert _until(lambda: any("lost the GCS" in n for n in notices), 10.0), notices
        assert not client.connected
        gcs = _Gcs(endpoint, mission)  # a GCS back on the same endpoint
        assert _until(lambda: client.connected, 30.0), notices
        assert any("connected to the GCS" in n for n in notices[1:]), notices
        assert console.run_line("status"), out[-2:]
    finally:
        client.close()
        link.close()
        gcs.close()
