"""Modbus TCP connections: framing, a bound on their number, an idle timeout, backpressure.

`ModbusTcpListener` accepts Modbus TCP clients on an asyncio loop and hands every complete
request to an `answer` coroutine (the strain server's), one request after another per
connection, in the order they came:

* **Framing.** A request is the 7-byte MBAP header (transaction id, protocol id, length, unit
  id) and `length - 1` bytes of PDU. Requests may arrive several to a TCP segment
  (pipelined) or one split over many; each is answered, in order, with the request's
  transaction and unit id. A protocol id other than 0 or a length outside 2 ... 254 (a PDU
  is at most 253 bytes) cannot be resynchronised on a byte stream: the connection is closed.
* **A bound on connections.** At most `max_connections` are open. A new connection beyond it
  is always admitted and the oldest idle one is dropped to make room: first the connections
  that never sent a complete request (oldest first), then the one whose last request is the
  oldest. A controller that polls therefore keeps its connection through a flood of idle or
  half-open ones, and one that connects always gets in.
* **Idle timeout.** A connection that sends no complete request for `idle_timeout_s` (silent,
  or stuck in a partial header or PDU) is closed; so is one whose answers cannot be sent for
  as long (a client that never reads: its answers wait in buffers of 64 KiB, the kernel's
  and the server's, and its requests are not read meanwhile).
* **Fairness.** Every connection yields to the others after each request, so a client that
  pipelines thousands of requests gets one answer per turn like everyone else.
* **A bounded log.** Dropped, timed-out and broken connections go to a `ThrottledLog`: one
  line per kind and interval, with a count, never a traceback.

What it does not do: it does not know Modbus functions or registers (`answer` does), and it
has no TLS.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from appliance.live.throttled_log import ThrottledLog

MBAP_HEADER = struct.Struct(">HHHB")
"""Transaction id, protocol id (0 for Modbus), length (unit id + PDU bytes), unit id."""

MAX_MBAP_LENGTH = 254
"""Unit id and the longest PDU (253 bytes)."""

LISTEN_BACKLOG = 256
"""Connections the kernel holds for the server to accept: a flood must not crowd out a
controller's connect before the server gets to drop the flood's oldest idle connections."""

WRITE_BUFFER_BYTES = 65536
"""Answers waiting to be sent on a connection, in the kernel and again in the server, before
its requests are no longer read."""

READ_BUFFER_BYTES = 65536
"""Requests the kernel holds for a connection that the server is not reading (about 5000)."""

Answer = Callable[[int, bytes, str | None], Awaitable[bytes | None]]
"""answer(unit_id, request PDU, client IP) -> the response PDU, or None to send nothing."""


class _FramingError(Exception):
    """A header that cannot start a Modbus TCP request: the byte stream is lost."""


@dataclass(eq=False)
class _Connection:
    writer: asyncio.StreamWriter
    peer: str
    name: str
    opened_s: float
    last_request_s: float | None = None
    dropped: bool = False

    def eviction_order(self) -> tuple[bool, float]:
        """Sorts the first to drop first: never served, then the longest idle."""
        if self.last_request_s is None:
            return (False, self.opened_s)
        return (True, self.last_request_s)


class ModbusTcpListener:
    """Serves Modbus TCP on (host, port) with bounded connections, as the module says.

    Args:
        host, port: where to listen.
        answer: the coroutine that answers one request (see `Answer`).
        max_connections: connections open at once; beyond it the oldest idle is dropped.
        idle_timeout_s: a connection without a complete request for this long is closed.
        log: where dropped and broken connections are reported.
    """

    def __init__(
        self,
        host: str,
        port: int,
        answer: Answer,
        *,
        max_connections: int,
        idle_timeout_s: float,
        log: ThrottledLog,
    ) -> None:
        self.host = host
        self.port = port
        self._answer = answer
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self._log = log
        self._connections: set[_Connection] = set()
        self._server: asyncio.Server | None = None

    @property
    def connections(self) -> int:
        """Connections open now."""
        return len(self._connections)

    async def start(self) -> None:
        """Listen (raises OSError when the address cannot be bound)."""
        self._server = await asyncio.start_server(
            self._serve,
            self.host,
            self.port,
            backlog=LISTEN_BACKLOG,
            reuse_address=True,
        )

    async def close(self) -> None:
        """Stop listening and close every connection."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for connection in list(self._connections):
            connection.writer.transport.abort()
        self._connections.clear()
        if server is not None:
            await server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        connection = _Connection(
            writer,
            peer=peer[0] if peer else "",
            name=f"{peer[0]} port {peer[1]}" if peer else "an unknown peer",
            opened_s=time.monotonic(),
        )
        sock = writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, WRITE_BUFFER_BYTES)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, READ_BUFFER_BYTES)
        writer.transport.set_write_buffer_limits(high=WRITE_BUFFER_BYTES)
        self._admit(connection)
        try:
            await self._requests(connection, reader)
        except asyncio.IncompleteReadError:
            pass
        except TimeoutError:
            self._log.note(
                "idle",
                f"modbus tcp: closed a connection from {connection.name}: no complete request, "
                f"or no room for its answers, for {self.idle_timeout_s:g} s "
                "([modbus] idle_timeout_s)",
            )
        except _FramingError as exc:
            self._log.note(
                "framing", f"modbus tcp: closed a connection from {connection.name}: {exc}"
            )
        except (ConnectionError, OSError) as exc:
            if connection.dropped:
                return
            self._log.note(
                "broken",
                f"modbus tcp: a connection from {connection.name} broke: "
                f"{exc.strerror or type(exc).__name__}",
            )
        finally:
            self._connections.discard(connection)
            writer.transport.abort()

    def _admit(self, connection: _Connection) -> None:
        while len(self._connections) >= self.max_connections:
            victim = min(self._connections, key=_Connection.eviction_order)
            self._connections.discard(victim)
            victim.dropped = True
            victim.writer.transport.abort()
            self._log.note(
                "dropped",
                f"modbus tcp: dropped the oldest idle connection (from {victim.name}) to let "
                f"{connection.name} in ([modbus] max_connections = {self.max_connections})",
            )
        self._connections.add(connection)

    async def _requests(self, connection: _Connection, reader: asyncio.StreamReader) -> None:
        writer = connection.writer
        while True:
            async with asyncio.timeout(self.idle_timeout_s):
                header = await reader.readexactly(MBAP_HEADER.size)
                transaction_id, protocol_id, length, unit_id = MBAP_HEADER.unpack(header)
                if protocol_id != 0:
                    raise _FramingError(f"protocol id {protocol_id} is not Modbus (0)")
                if not 2 <= length <= MAX_MBAP_LENGTH:
                    raise _FramingError(f"MBAP length {length} outside 2 ... {MAX_MBAP_LENGTH}")
                pdu = await reader.readexactly(length - 1)
            connection.last_request_s = time.monotonic()
            response = await self._answer(unit_id, pdu, connection.peer)
            await asyncio.sleep(0)
            if response is None:
                continue
            writer.write(MBAP_HEADER.pack(transaction_id, 0, len(response) + 1, unit_id) + response)
            async with asyncio.timeout(self.idle_timeout_s):
                await writer.drain()
