"""The one MCAP writer of felis (`McapLog`): channels in a Foxglove SDK context, written to a chunked, indexed file
and, with a `felis.logs.live.LiveView`, served live. What a log holds and when its chunks are finished (the crash
bound): `felis.logs.runlog`."""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Iterator
from pathlib import Path

import foxglove
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import Timestamp

from felis.errors import LogError
from felis.files import prepare_parent
from felis.logs import sdk
from felis.logs.background import Background
from felis.logs.schemas import _text, jsonable, schema_of

MAGIC = b"\x89MCAP0\r\n"
PROFILE = ""  # Foxglove's well-known schemas in protobuf and JSON: no ROS profile
BACKGROUND = True  # chunks are written by a writer thread (`felis.logs.background`); False: on the loop's thread
COMPRESSION = MCAPCompression.Lz4  # per chunk; lz4 and zstd cost about the same at this chunk size
FLUSH_S = 0.04  # a chunk is finished at least this often (run time); a killed process loses at most twice this, plus
# two ticks (`felis.logs.runlog`, "Crash safety")
FLUSH_WALL_S = FLUSH_S / 2  # … and not more often than this (wall time): a simulation faster than real time
FAST = 2.0  # a run this many times faster than real time finishes its chunks on its own thread (`McapLog._boundary`)

# ---------------------------------------------------------------------------------------------
# writing


def _remove_old(path: Path) -> None:
    """Unlink an old log at ``path`` before a new one is written there: the file system frees an unlinked file
    about fifty times faster than it truncates one on open (ext4: 0.05 ms against 2.4 ms for a 2 s cat log,
    ``bench/sim_speed.py`` writes one per episode). A symbolic link is left alone (written through, as
    before); a file that cannot be removed is left for the open to report."""
    try:
        if path.is_file() and not path.is_symlink():
            path.unlink()
    except OSError:
        pass


def _stamp(ns: int) -> Timestamp:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(sec=sec, nsec=nsec)


class McapLog:
    """The one MCAP writer of felis: channels in a Foxglove SDK context, written to ``path`` (chunked, indexed,
    flushed every `FLUSH_S` of log time) and, when ``live`` is given, served by that `LiveView` too.

    ``path`` may be None (a live view only). ``meta`` is the ``/meta`` message (JSON, its schema from its
    values) written first at log time ``start_ns``. Errors: ``error(f"cannot write {what} {path}: …")``.
    """

    def __init__(self, path: str | Path | None, meta: dict, *, what: str = "run log",
                 error: type[Exception] = LogError, live=None):
        self.path = None if path is None else Path(path)
        self._what, self._error = what, error
        self._closed = False
        self.start_ns = time.time_ns()
        self._last_ns = self.start_ns
        self._flushed_ns = self.start_ns
        self._flushed_wall = time.monotonic_ns()
        self._next_ns = self.start_ns + FLUSH_NS  # log time of the next look at the chunk (`_boundary`)
        self._next_t = FLUSH_S  # … as run time (s)
        self._contexts = []
        self._writer = None
        self.live = live
        self._pending: list[tuple] = []  # deferred writes (`defer`)
        self._bg: Background | None = None  # the writer thread, from the first chunk handed over
        if self.path is not None:
            prepare_parent(self.path, what, error)
            _remove_old(self.path)
            ctx = foxglove.Context()
            options = MCAPWriteOptions(compression=COMPRESSION, chunk_size=None, profile=PROFILE,
                                       compression_level=1, compression_threads=0)
            try:
                self._writer = foxglove.open_mcap(self.path, allow_overwrite=True, context=ctx,
                                                  writer_options=options)
            except (OSError, RuntimeError, ValueError) as e:
                raise error(f"cannot write {what} {self.path}: {getattr(e, 'strerror', None) or e}") from None
            sdk.quiet()  # `felis.logs.sdk`: no SDK log records under its locks
            self._contexts.append(ctx)
        if live is not None:
            self._contexts.append(live.context)
        self._outs: dict[str, tuple] = {}
        self.meta = jsonable(meta)
        self.latched("/meta", schema_of(self.meta, "felis.Meta"), _text(self.meta), self.start_ns)
        self.flush()

    # -- channels -------------------------------------------------------------------------------

    def channel(self, topic: str, schema: dict | foxglove.Schema, encoding: str = "json"):
        """A function ``put(ns, data: bytes)`` that logs on ``topic`` to the file and the live view; ``put.many(ns,
        messages)`` logs a batch."""
        if isinstance(schema, dict):
            chans = [foxglove.Channel(topic, schema=schema, context=c) for c in self._contexts]
        else:
            chans = [foxglove.Channel(topic, schema=schema, message_encoding=encoding, context=c)
                     for c in self._contexts]
        logs = tuple(c.base.log for c in chans)
        if self.live is None:
            one = logs[0]

            def put(ns: int, data: bytes) -> None:
                one(data, ns)

            def many(ns: list[int], msgs: list[bytes]) -> None:
                for n, m in zip(ns, msgs, strict=True):
                    one(m, n)
        else:
            self.live.register(topic, chans[-1])
            watched = self.live.watchers(topic)
            live_log = logs[-1]
            file_log = logs[0] if len(logs) > 1 else None

            def put(ns: int, data: bytes) -> None:
                if file_log is not None:
                    file_log(data, ns)
                if watched[0]:
                    live_log(data, ns)

            def many(ns: list[int], msgs: list[bytes]) -> None:
                for n, m in zip(ns, msgs, strict=True):
                    if file_log is not None:
                        file_log(m, n)
                    if watched[0]:
                        live_log(m, n)
        put.many = many  # a batch: ``put.many(times, messages)``, one Python call fewer per message
        self._outs[topic] = (chans, put)
        return put

    def latched(self, topic: str, schema, data: bytes, ns: int, encoding: str = "json") -> None:
        """Log one message that a viewer needs whenever it connects (meta, scene): written once to the file
        and sent again to each live client that subscribes."""
        put = self.channel(topic, schema, encoding)
        self._check_open()
        put(ns, data)
        self._last_ns = max(self._last_ns, ns)
        if self.live is not None:
            self.live.latch(topic, data, ns)

    # -- deferred writing -------------------------------------------------------------------------

    def defer(self, fn, *args) -> None:
        """Run ``fn(*args)`` (an encode and write) at the next chunk boundary, with the other deferred ones in
        order, on the writer thread (`felis.logs.background`): at most `FLUSH_S` of run time later, when the chunk
        is finished anyway, so a crash loses no more than before. Why: writes done together cost less than one at
        a time between physics steps (`felis.logs.runlog`, "Speed"). ``fn`` must not touch what the loop's thread
        changes after this call."""
        self._pending.append((fn, args))

    def _take(self):
        """The deferred work so far, taken out of the log (what `_steps` writes)."""
        pending, self._pending = self._pending, []
        return pending

    def _steps(self, pending) -> Iterator[None]:
        """Write what `_take` took, yielding between small slices of the work (`felis.logs.background`)."""
        for fn, args in pending:
            fn(*args)
            yield

    def _write_pending(self) -> None:
        """Write what is deferred now, on this thread."""
        for _ in self._steps(self._take()):
            pass

    def _job(self, data) -> Iterator[None]:
        """The writer thread's job: the deferred writes taken, then the chunk finished."""
        yield from self._steps(data)
        if self._writer is not None:
            self._writer.flush()

    def _handoff(self) -> None:
        """Finish the chunk: its deferred writes and the finishing go to the writer thread
        (`felis.logs.background`), after the job handed over before if the writer has not done it yet (so at most
        one is unwritten); without `BACKGROUND`, now."""
        if not BACKGROUND:
            self.flush()
            return
        bg = self._bg
        if bg is None:
            self._bg = bg = Background()
            weakref.finalize(self, bg.abandon)  # a log dropped without close: its writer (and the switch interval) go
        elif bg.pending:
            self._background(bg.drain)
        bg.submit(self._job(self._take()))

    def _background(self, fn) -> None:
        try:
            fn()
        except (OSError, RuntimeError) as e:
            raise self._error(f"cannot write {self._what} {self.path}: {e}") from None

    def message(self, topic: str, t: float, msg: dict, schema: dict | None = None) -> None:
        """Write the JSON ``msg`` on ``topic`` at run time ``t`` (s); the channel is made on first use with
        ``schema`` (default: from ``msg``)."""
        self._check_open()
        self._message(topic, t, jsonable(msg), schema)

    def _message(self, topic: str, t: float, msg, schema) -> None:
        out = self._outs.get(topic)
        put = out[1] if out else self.channel(topic, schema or schema_of(msg, f"felis.{topic.strip('/').title()}"))
        ns = self.ns(t)
        self._tick(ns)
        put(ns, _text(msg))

    def ns(self, t: float) -> int:
        """Log time (epoch ns) of run time ``t`` (s); non-finite or negative times map to the start."""
        return self.start_ns + (int(round(t * 1e9)) if math.isfinite(t) and t > 0 else 0)

    def _tick(self, ns: int) -> None:
        if ns > self._last_ns:
            self._last_ns = ns
        if ns >= self._next_ns:
            self._boundary(ns)
        bg = self._bg
        if bg is not None:
            if bg.error is not None:
                self._background(bg.check)
            bg.nudge()

    def _boundary(self, ns: int) -> None:
        """`FLUSH_S` of run time has passed since the last chunk: finish it if `FLUSH_WALL_S` of wall time has
        too, else (faster than real time) look again when the wall clock is likely to have caught up halfway, and
        at least every `FLUSH_S` / 4 of run time or a quarter of the run time since the last chunk, whichever is
        longer (the crash bound's slack; a look costs a clock read, and a simulation 50 times faster than real
        time would otherwise look every tick).

        Who finishes the chunk: the writer thread (`_handoff`) when the run keeps pace with the clock (it waits
        each tick, and the writer works then); this thread when the run is more than `FAST` times faster than
        real time (a simulation that never waits: there the writer only competes with the loop for the
        interpreter and the CPU, measured 0.62–0.65 of a bare loop against 0.65–0.66 without it,
        ``bench/sim_speed.py --with-log``)."""
        wall = time.monotonic_ns()
        waited = wall - self._flushed_wall
        ran = ns - self._flushed_ns
        if waited >= FLUSH_WALL_NS:
            if ran > FAST * waited:
                self.flush()
            else:
                self._handoff()
            self._flushed_ns, self._flushed_wall = ns, wall
            self._next_ns = ns + FLUSH_NS
        else:
            look = min(max(FLUSH_NS // 4, ran // 4), (FLUSH_WALL_NS - waited) * ran // max(1, 2 * waited))
            self._next_ns = ns + max(1, look)
        self._next_t = (self._next_ns - self.start_ns) * 1e-9

    def flush(self) -> None:
        """Write what is deferred, finish the current chunk and hand it to the operating system."""
        if self._bg is not None:
            self._background(self._bg.drain)
        self._write_pending()
        if self._writer is not None:
            try:
                self._writer.flush()
            except (OSError, RuntimeError) as e:
                raise self._error(f"cannot write {self._what} {self.path}: {e}") from None

    def _check_open(self) -> None:
        if self._closed:
            raise self._error(f"{self._what} {self.path} is closed; cannot log")

    def close(self, summary: dict | None = None) -> None:
        """Write ``/summary`` (if given) and finish the file (summary section, footer). Idempotent."""
        if self._closed:
            return
        try:
            if self._bg is not None:
                bg, self._bg = self._bg, None
                self._background(bg.close)
            self._write_pending()
            if summary is not None:
                s = jsonable(summary)
                put = self.channel("/summary", schema_of(s, "felis.Summary"))
                put(self._last_ns, _text(s))
            if self._writer is not None:
                self._writer.close()
        except (OSError, RuntimeError) as e:
            raise self._error(f"cannot finish {self._what} {self.path}: {e}") from None
        finally:
            self._closed = True
            registry = getattr(getattr(foxglove, "channel", None), "_channels_by_id", None)
            for chans, _ in self._outs.values():
                for c in chans:
                    c.close()
                    if isinstance(registry, dict):  # the SDK keeps every channel it made: let ours go
                        registry.pop(c.id(), None)
            if self.live is not None:
                self.live.unlatch()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


FLUSH_NS = int(FLUSH_S * 1e9)
FLUSH_WALL_NS = int(FLUSH_WALL_S * 1e9)
