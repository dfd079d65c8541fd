"""A TCP relay that delays every byte by a fixed latency plus jitter, each direction, in order: the
delay fault of docs/reliability.md N3 on a host without `tc netem`. Zenoh links (plain TCP or TLS) pass
through it unchanged; only their timing is.

    with DelayRelay(listen_port, "127.0.0.1", router_port, delay_s=0.1, jitter_s=0.02) as relay:
        ...  # clients connect to tcp/127.0.0.1:<listen_port>

Chunks are released at `arrival + delay + uniform(-jitter, +jitter)`, never before the previous chunk
of the same direction (TCP keeps order, so jitter can only bunch data, not reorder it).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
import time
from types import TracebackType

CHUNK_BYTES = 65536


class DelayRelay:
    """Runs on its own thread with its own event loop; `close` (or leaving the `with`) stops it."""

    def __init__(
        self, listen_port: int, host: str, port: int, delay_s: float, jitter_s: float = 0.0, seed: int = 0
    ) -> None:
        if delay_s < 0 or not 0 <= jitter_s <= delay_s:
            raise ValueError("need delay_s >= 0 and 0 <= jitter_s <= delay_s")
        self.listen_port, self.host, self.port = listen_port, host, port
        self.delay_s, self.jitter_s = delay_s, jitter_s
        self._rng = random.Random(seed)
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="delay-relay")
        self.connections = 0
        self.bytes_relayed = 0

    def __enter__(self) -> DelayRelay:
        self._thread.start()
        if not self._ready.wait(5.0):
            raise RuntimeError("delay relay did not start")
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5.0)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        server = self._loop.run_until_complete(
            asyncio.start_server(self._accept, "127.0.0.1", self.listen_port)
        )
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:
            server.close()
            for task in asyncio.all_tasks(self._loop):
                task.cancel()
            with contextlib.suppress(Exception):
                self._loop.run_until_complete(asyncio.sleep(0))
            self._loop.close()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection(self.host, self.port)
        except OSError:
            writer.close()
            return
        self.connections += 1
        await asyncio.gather(
            self._pump(reader, up_writer), self._pump(up_reader, writer), return_exceptions=True
        )

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

        async def release() -> None:
            while True:
                due_s, data = await queue.get()
                if not data:
                    break
                await asyncio.sleep(max(0.0, due_s - time.monotonic()))
                writer.write(data)
                await writer.drain()
                self.bytes_relayed += len(data)

        sender = asyncio.ensure_future(release())
        last_due = 0.0
        try:
            while data := await reader.read(CHUNK_BYTES):
                jitter = self._rng.uniform(-self.jitter_s, self.jitter_s)
                last_due = max(last_due, time.monotonic() + self.delay_s + jitter)
                await queue.put((last_due, data))
        finally:
            await queue.put((last_due, b""))
            with contextlib.suppress(Exception):
                await sender
            writer.close()
