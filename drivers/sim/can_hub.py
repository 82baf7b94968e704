"""A python-can-remote hub in this process, so that other processes can hear the simulated CAN node.

``can_remote.RemoteServer`` is a threading HTTP/WebSocket server; every client that connects gets its own
bus built from the server's config, here a python-can ``virtual`` bus on ``channel``. The simulated node
sends on another ``virtual`` bus on the same channel, so every remote client receives its frames::

    hub = CanHub("ws://127.0.0.1:54701/", channel="chtc-sim")
    hub.start()
    node_bus = can.Bus(interface="virtual", channel="chtc-sim", ignore_config=True)
    # elsewhere: can.Bus(interface="remote", channel=hub.url)

Port 0 in the URL binds a free port (see :attr:`url`). Errors: ``DeviceUnavailableError`` when the port
cannot be bound.
"""

from __future__ import annotations

import threading
from urllib.parse import urlparse

from can_remote import RemoteServer

from drivers.errors import DeviceUnavailableError

__all__ = ["DEFAULT_HUB_URL", "CanHub"]

DEFAULT_HUB_URL = "ws://127.0.0.1:54701/"


class CanHub:
    """A python-can-remote server on a thread; clients get a ``virtual`` bus on ``channel``."""

    def __init__(self, url: str, channel: str) -> None:
        parsed = urlparse(url if "://" in url else f"ws://{url}")
        self.host = parsed.hostname or "127.0.0.1"
        self.port = parsed.port if parsed.port is not None else 54701
        try:
            self.server = RemoteServer(self.host, self.port, interface="virtual", channel=channel)
        except OSError as err:
            raise DeviceUnavailableError(f"cannot listen: {err}", device=f"can hub {url}") from err
        self.port = int(self.server.server_port)
        self._thread = threading.Thread(
            target=self.server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True
        )

    @property
    def url(self) -> str:
        """The channel remote clients use."""
        return f"ws://{self.host}:{self.port}/"

    def start(self) -> None:
        """Serve on the thread."""
        self._thread.start()

    def stop(self) -> None:
        """Stop accepting and close the listening socket (client threads are daemons)."""
        self.server.shutdown()
        self.server.server_close()
