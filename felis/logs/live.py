"""The live view (``--live [HOST:]PORT``): a run's log channels served over the Foxglove WebSocket protocol
(``foxglove.start_server``), so Foxglove (or Lichtblick) shows the robot while it runs.

Bound to 127.0.0.1 unless a host is given; nothing listens without the flag. The server runs on the SDK's own
threads and keeps a bounded queue per client (the oldest messages are dropped when a client is slow), so the
control loop never waits on a viewer (`bench/sim_speed.py --with-log`); a message on a channel no client
subscribes to is not handed to the server at all. The run log hands over each tick's messages in batches, when it
finishes a chunk (`felis.logs.runlog`, "Speed"): a viewer sees the run at most 0.1 s late at 100 Hz.
Messages a viewer needs whenever it connects (``/meta``, the
``/robot`` scene) are latched: sent again to each client that subscribes to them.
"""

from __future__ import annotations

import threading

import foxglove
from foxglove.websocket import ServerListener

from felis.errors import ParameterError
from felis.logs import sdk

DEFAULT_HOST = "127.0.0.1"


def parse_address(text: str) -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (``[v6]:PORT``) → (host, port); the host defaults to 127.0.0.1; port 0 picks a
    free one."""
    s = str(text).strip()
    host, sep, port = s.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, s
    host = host.strip("[]") or DEFAULT_HOST
    try:
        p = int(port)
    except ValueError:
        raise ParameterError(f"--live {text!r}: expected [HOST:]PORT, e.g. 8765 or 0.0.0.0:8765") from None
    if not 0 <= p <= 65535:
        raise ParameterError(f"--live {text!r}: port must be within 0…65535")
    return host, p


class _Latch(ServerListener):
    def __init__(self, view: LiveView):
        self.view = view

    def on_subscribe(self, client, channel) -> None:
        self.view._count(channel.topic, +1)
        self.view._resend(channel.topic)

    def on_unsubscribe(self, client, channel) -> None:
        self.view._count(channel.topic, -1)


class LiveView:
    """A Foxglove WebSocket server on its own SDK context; `felis.logs.mcap.McapLog` logs to ``context``."""

    def __init__(self, address: str | tuple[str, int], name: str = "felis"):
        host, port = parse_address(address) if isinstance(address, str) else address
        self.context = foxglove.Context()
        self._latched: dict[str, tuple[bytes, int]] = {}
        self._lock = threading.Lock()
        self._channels: dict[str, object] = {}
        self._watchers: dict[str, list[int]] = {}
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                                server_listener=_Latch(self))
        except (OSError, RuntimeError, ValueError) as e:
            raise ParameterError(f"--live {host}:{port}: cannot serve: {e}") from None
        sdk.quiet()  # else closing a channel while a viewer subscribes can deadlock (`felis.logs.sdk`)
        self.host, self.port = host, self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def watchers(self, topic: str) -> list[int]:
        """A one-element list holding how many clients subscribe to ``topic`` now (updated in place by the
        server's thread): the log skips the live copy of a message nobody watches."""
        with self._lock:
            return self._watchers.setdefault(topic, [0])

    def _count(self, topic: str, step: int) -> None:
        with self._lock:
            w = self._watchers.setdefault(topic, [0])
            w[0] = max(0, w[0] + step)

    def latch(self, topic: str, data: bytes, ns: int) -> None:
        with self._lock:
            self._latched[topic] = (data, ns)

    def unlatch(self) -> None:
        with self._lock:
            self._latched.clear()

    def _resend(self, topic: str) -> None:
        with self._lock:
            item = self._latched.get(topic)
        if item is None:
            return
        chan = self._channels.get(topic)
        if chan is not None:
            chan.base.log(item[0], item[1])

    def register(self, topic: str, channel) -> None:
        """The live channel of ``topic`` (for latched re-sends)."""
        self._channels[topic] = channel

    def close(self) -> None:
        self.server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
