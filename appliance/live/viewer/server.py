"""The gRPC server remote Rerun viewers connect to, up for as long as the service runs.

One server across tests
-----------------------
In rerun 0.41 a gRPC server exists only as the sink (`rr.GrpcServerSink`) of a recording stream:
replacing that stream's sinks or dropping the stream shuts the server down (rerun issue #12313,
"serve_grpc() should be possible to use independently of recording stream"). A server on each
test's stream would go down between tests and every viewer would lose its connection. So the
server lives on a stream of its own, `RerunService`, which holds nothing but a note and lasts as
long as the service; each test's stream is a *client* of that server (`rr.GrpcSink` to its
local URL), and the server relays every test to every connected viewer as a new recording. A
viewer that connects late still gets what the server kept (`server_memory_limit`; static data
is always kept). A `RerunViewer` opens its own `RerunService` (or takes one to share) at
`start()` and keeps it until `close()`, so one viewer serves every test of the service.

A quirk of rerun 0.41: the server shuts down gracefully, only once the last connected viewer has
hung up, so a viewer connected to a closed service keeps the port bound until the process ends.
A viewer's `rerun --save` therefore completes its file when the serving process exits.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import time

import rerun as rr

from appliance.config import parse_address
from appliance.errors import InputError
from appliance.live.viewer.layout import APPLICATION_ID

logger = logging.getLogger("appliance.live.viewer")

_LISTEN_WAIT_S = 2.0


def proxy_url(host: str, port: int) -> str:
    """The URL a viewer opens for a gRPC server at `host`:`port` (IPv6 in brackets)."""
    shown = f"[{host}]" if ":" in host else host
    return f"rerun+http://{shown}:{port}/proxy"


class RerunService:
    """A gRPC server that remote Rerun viewers connect to, up for as long as the service runs.

    The server is the only sink of a recording stream of its own (the "service" recording,
    which holds a note saying what this is); the viewer of each test connects its own stream
    to `local_url`, and the server relays every test to every viewer connected to `url`. See
    the module docstring for why (rerun 0.41 ties a server to a stream).

    Args:
        serve: "HOST:PORT" to listen on, HOST an IP address (`[rerun] serve`): 127.0.0.1 for
            viewers on this computer only (or through an SSH tunnel), 0.0.0.0 (or ::) for
            viewers on the lab network.
        application_id: the Rerun application id shared by the service and its tests.
        server_memory_limit: how much history the server keeps for viewers that connect
            late, in rerun's syntax ("512MiB", "10%"); the oldest goes first, static data
            stays.
        where: the configuration key named in errors.

    Raises:
        InputError: one line naming `where` and the address: the address is malformed, not
            an IP address, or not available ("[rerun] serve: cannot listen on
            127.0.0.1:9876 (Address already in use)").

    Attributes:
        host, port: the address listened on.
        url: what a remote viewer opens (`rerun <url>`).
        local_url: what this process's recordings connect to (loopback when listening on
            every interface).
        server_memory_limit: the history kept for late viewers, as given.
    """

    def __init__(
        self,
        serve: str,
        *,
        application_id: str = APPLICATION_ID,
        server_memory_limit: str = "512MiB",
        where: str = "[rerun] serve",
    ) -> None:
        host, port = parse_address(serve, where)
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            raise InputError(f"{where}: HOST must be an IP address, got {host!r}") from None
        _check_can_listen(host, port, where)
        self.host = host
        self.port = port
        self.url = proxy_url(host, port)
        local = ("::1" if address.version == 6 else "127.0.0.1") if address.is_unspecified else host
        self.local_url = proxy_url(local, port)
        self.server_memory_limit = server_memory_limit
        self._stream = rr.RecordingStream(
            application_id, recording_id=f"{application_id}-service", send_properties=False
        )
        self._stream.set_sinks(
            rr.GrpcServerSink(bind_ip=host, port=port, server_memory_limit=server_memory_limit)
        )
        if not _wait_listening(local, port, _LISTEN_WAIT_S):
            self._stream.disconnect()
            raise InputError(
                f"{where}: cannot listen on {_host_port(host, port)} (no server came up)"
            )
        self._stream.log(
            "service",
            rr.TextDocument(
                f"Extensometer service, serving on {self.url}. "
                "Every test arrives as a recording of its own."
            ),
            static=True,
        )
        self.closed = False

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the server (idempotent); viewers still connected keep it up until they hang up."""
        if self.closed:
            return
        self.closed = True
        try:
            self._stream.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            logger.warning("rerun service: %s", one_line(exc))
        self._stream.disconnect()

    def __enter__(self) -> RerunService:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _host_port(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _check_can_listen(host: str, port: int, where: str) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise InputError(f"{where}: cannot listen on {_host_port(host, port)} ({reason})") from None


def _wait_listening(host: str, port: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())
