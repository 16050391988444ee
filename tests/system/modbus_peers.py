"""Real Modbus peers for the strain server's tests: mbpoll, a socat pty pair, free ports.

mbpoll (libmodbus) is the client a test runs against the server as a subprocess; socat makes
a pair of linked ptys, the server on one end and mbpoll on the other, for Modbus RTU. Both
are skipped with a clear reason when missing. Every process started here is ended by the
context manager or helper that started it.
"""

from __future__ import annotations

import contextlib
import math
import re
import shutil
import socket
import struct
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest

from appliance.config import Config
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.gauges import Calibration, Gauge, StrainGaugesLayout, StrainReading
from appliance.run.outputs import RunFacts
from hal.camera.base import Frame
from hal.machine.base import MachineState

MBPOLL = shutil.which("mbpoll")
SOCAT = shutil.which("socat")

needs_mbpoll = pytest.mark.skipif(
    MBPOLL is None, reason="mbpoll is not installed (apt-get install mbpoll)"
)
needs_socat = pytest.mark.skipif(
    SOCAT is None, reason="socat is not installed (apt-get install socat)"
)

MBPOLL_TIMEOUT_S = 5.0
"""mbpoll's response timeout (-o): generous, for a loaded 2-core host."""

_VALUE_LINE = re.compile(r"^\[(\d+)\]:\s+(\S+)(?:\s+\(-?\d+\))?\s*$", re.MULTILINE)
"""A value line; a 16-bit value >= 32768 is followed by its signed reading in parentheses."""


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def mbpoll(
    *args: str, response_timeout_s: float = MBPOLL_TIMEOUT_S, timeout_s: float = 60.0
) -> subprocess.CompletedProcess:
    """Run mbpoll with `args` and a response timeout (-o); never raises on failure."""
    assert MBPOLL is not None
    return subprocess.run(
        [MBPOLL, "-o", f"{response_timeout_s:g}", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def mbpoll_tcp(
    port: int,
    *options: str,
    write: Sequence[str] = (),
    response_timeout_s: float = MBPOLL_TIMEOUT_S,
) -> subprocess.CompletedProcess:
    """mbpoll over TCP to 127.0.0.1:port, zero-based addresses; writes `write` if given.

    mbpoll takes the values to write after the host, behind "--" (so negatives are values).
    """
    values = ("--", *write) if write else ()
    return mbpoll(
        "-m",
        "tcp",
        "-p",
        str(port),
        "-0",
        *options,
        "127.0.0.1",
        *values,
        response_timeout_s=response_timeout_s,
    )


def mbpoll_read_tcp(port: int, *args: str) -> dict[int, str]:
    """One poll over TCP; the values mbpoll printed by address (asserts it succeeded)."""
    done = mbpoll_tcp(port, "-1", *args)
    assert done.returncode == 0, done.stdout + done.stderr
    return printed_values(done.stdout)


def printed_values(stdout: str) -> dict[int, str]:
    """mbpoll's "[address]: value" lines as {address: text} (unsigned for 16-bit values)."""
    return {int(address): text for address, text in _VALUE_LINE.findall(stdout)}


@contextlib.contextmanager
def pty_pair(directory: Path, timeout_s: float = 20.0) -> Iterator[tuple[str, str]]:
    """Two linked ptys made by socat, as (server end, client end) paths; socat ended after."""
    assert SOCAT is not None
    server_end, client_end = directory / "ttyA", directory / "ttyB"
    process = subprocess.Popen(
        [
            SOCAT,
            "-d",
            "-d",
            f"pty,raw,echo=0,link={server_end}",
            f"pty,raw,echo=0,link={client_end}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not (server_end.exists() and client_end.exists()):
            if process.poll() is not None:
                message = process.stderr.read() if process.stderr else ""
                raise RuntimeError(f"socat exited: {message}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"socat made no pty pair within {timeout_s:g} s")
            time.sleep(0.02)
        yield str(server_end), str(client_end)
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)
        if process.stderr is not None:
            process.stderr.close()


def make_sample(
    *,
    strain: float = 0.123456,
    transverse: float = -0.0321,
    elongation_mm: float = 6.1728,
    gauge_length_mm: float = 56.1728,
    poisson: float = 0.26,
    frame_id: int = 70_000,
    timestamp_ns: int = 1_234_567_890,
    time_s: float = 12.5,
    status: tuple[int, ...] = (0, 0, 0, 0),
    data_valid: bool = True,
    reference_updates: int = 0,
    machine: MachineState | None = None,
    latency_s: float = 0.00125,
    frames_dropped: int = 0,
) -> StrainSample:
    """A sample with known numbers, built directly (no tracking)."""
    count = len(status)
    reading = StrainReading(
        axial_px=100.0 * (1 + strain),
        engineering_strain=strain,
        true_strain=math.log1p(strain) if strain > -1 else math.nan,
        elongation_mm=elongation_mm,
        gauge_length_mm=gauge_length_mm,
        transverse_strain=transverse,
        poisson_ratio=poisson,
    )
    return StrainSample(
        index=0,
        frame_id=frame_id,
        timestamp_ns=timestamp_ns,
        time_s=time_s,
        exposure_us=100.0,
        reading=reading,
        positions=np.zeros((count, 2)),
        status=np.asarray(status, dtype=np.int8),
        zncc=np.ones(count),
        gradients=np.zeros((count, 4)),
        data_valid=data_valid,
        reference_updates=reference_updates,
        machine=machine,
        latency_s=latency_s,
        frames_dropped=frames_dropped,
    )


def make_facts(epoch_offset_ns: int = 1_700_000_000_000_000_000) -> RunFacts:
    """Run facts whose only figure that matters here is the device-to-UNIX time offset."""
    points = np.array([[10.0, 10.0], [12.0, 10.0], [10.0, 60.0], [12.0, 60.0]])
    layout = StrainGaugesLayout(axial=Gauge((0, 1), (2, 3)), transverse=None)
    reference = Frame(
        image=np.zeros((80, 30), dtype=np.uint8), frame_id=0, timestamp_ns=0, exposure_us=100.0
    )
    return RunFacts(
        config=Config(),
        reference=reference,
        points=points,
        marks=((0, 1), (2, 3)),
        layout=layout,
        calibration=Calibration(0.1),
        gauge_length_mm=5.0,
        epoch_offset_ns=epoch_offset_ns,
    )


MBAP_HEADER = struct.Struct(">HHHB")
"""Modbus TCP's MBAP header: transaction id, protocol id (0), length (unit id + PDU), unit id."""


def mbap(transaction_id: int, pdu: bytes, unit_id: int = 1, protocol_id: int = 0) -> bytes:
    """One Modbus TCP frame (ADU): the MBAP header and `pdu`."""
    return MBAP_HEADER.pack(transaction_id, protocol_id, len(pdu) + 1, unit_id) + pdu


def read_registers_pdu(address: int, count: int, function_code: int = 3) -> bytes:
    """A read holding (3) or input (4) registers request PDU."""
    return struct.pack(">BHH", function_code, address, count)


def split_frames(data: bytes) -> tuple[list[tuple[int, int, int, bytes]], bytes]:
    """Complete MBAP frames in `data` as (transaction id, protocol id, unit id, PDU), and the rest.

    A frame whose length field is below 2 ends the split (the rest is returned unsplit).
    """
    frames = []
    while len(data) >= MBAP_HEADER.size:
        transaction_id, protocol_id, length, unit_id = MBAP_HEADER.unpack_from(data)
        end = MBAP_HEADER.size - 1 + length
        if length < 2 or len(data) < end:
            break
        frames.append((transaction_id, protocol_id, unit_id, data[MBAP_HEADER.size : end]))
        data = data[end:]
    return frames, data


def receive_frames(
    sock: socket.socket, count: int, timeout_s: float = 10.0
) -> list[tuple[int, int, int, bytes]]:
    """Read from `sock` until `count` whole frames came, the peer closed or `timeout_s` passed."""
    data = b""
    deadline = time.monotonic() + timeout_s
    while True:
        frames, _ = split_frames(data)
        left_s = deadline - time.monotonic()
        if len(frames) >= count or left_s <= 0:
            return frames
        sock.settimeout(left_s)
        try:
            chunk = sock.recv(65536)
        except (TimeoutError, ConnectionError):
            return frames
        if not chunk:
            return frames
        data += chunk


def receive_until_closed(sock: socket.socket, timeout_s: float = 10.0) -> tuple[bytes, bool]:
    """Everything `sock` receives until the peer closes it: (bytes, whether it closed in time).

    A reset counts as closed.
    """
    data = b""
    deadline = time.monotonic() + timeout_s
    while (left_s := deadline - time.monotonic()) > 0:
        sock.settimeout(left_s)
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            break
        except ConnectionError:
            return data, True
        if not chunk:
            return data, True
        data += chunk
    return data, False


def is_closed_by_peer(sock: socket.socket) -> bool:
    """Whether the peer closed (or reset) `sock`, without waiting; unread data is discarded."""
    sock.setblocking(False)
    try:
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                return True
    except BlockingIOError:
        return False
    except ConnectionError:
        return True


def timed_read(port: int, timeout_s: float = 10.0, unit_id: int = 1) -> float:
    """Seconds one read of registers 0 ... 13 takes on a fresh connection (connect included).

    Raises:
        AssertionError: no valid answer within `timeout_s`.
    """
    started = time.monotonic()
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as sock:
        sock.sendall(mbap(4242, read_registers_pdu(0, 14), unit_id))
        frames = receive_frames(sock, 1, timeout_s)
    assert frames, f"no answer to a read within {timeout_s:g} s"
    transaction_id, _, _, pdu = frames[0]
    assert transaction_id == 4242 and pdu[:2] == bytes((3, 28)), frames[0]
    return time.monotonic() - started


_TCP_CLOSE_WAIT, _TCP_CLOSE = 8, 7
"""Linux TCP states (tcpi_state) of a socket whose peer has sent FIN, or reset it."""


def wait_closed_by_peer_unread(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the peer closes or resets `sock` within `timeout_s`, without reading from it.

    Reads the socket's TCP state (Linux TCP_INFO), so a client that never reads stays one.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        state = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0]
        if state in (_TCP_CLOSE_WAIT, _TCP_CLOSE):
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
