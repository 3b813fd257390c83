"""The Foxglove SDK's own log records, turned off: what keeps a live view from deadlocking the control loop.

The SDK (`foxglove-sdk` 0.30) forwards the log records of its Rust code to Python's `logging` through pyo3-log,
which takes the GIL. Its WebSocket server does that on its own thread while it holds a lock on a client's
channels (for example "Client … attempted to subscribe to unknown channel", when a viewer subscribes to a channel
the run has just closed). A Python thread that closes a channel (`McapLog.close`, at the end of every run or
episode) holds the GIL and waits for that lock: both wait forever. Seen as `bench/sim_speed.py --with-log` hanging
with one client connected; `tests/logs/test_live.py` provokes it (a client subscribing to unknown channels while
channels are made and closed) and hangs within seconds without this.

`quiet()` sets the Rust log level to off once the SDK has set its logging up (the SDK does that, once, in its first
`open_mcap` or `start_server`): no record reaches Python, so the server thread never asks for the GIL under that
lock. The SDK's messages are lost (they were warnings about viewers, on stderr). An operator who sets
``FOXGLOVE_LOG_LEVEL`` to debug the SDK gets its records as before, and the risk with them.
"""

from __future__ import annotations

import os


def quiet() -> None:
    """Turn the SDK's forwarding of its log records off (module doc); call it after each `foxglove.open_mcap` and
    `foxglove.start_server` (the first one sets the forwarding up, later calls cost nothing)."""
    if "FOXGLOVE_LOG_LEVEL" in os.environ:
        return
    from foxglove import _foxglove_py

    _foxglove_py.disable_logging()  # not re-exported by the SDK's Python package; present since its logging exists
