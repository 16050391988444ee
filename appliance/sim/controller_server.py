"""A simulated machine behind a real Modbus server: the controller end of the wire.

A simulated test normally reads the simulated machine in-process. With `[sim] controller =
"modbus-tcp"` the simulated machine is served instead by a pymodbus server on 127.0.0.1 and
read back through the appliance's own Modbus client (`hal.machine.modbus.ModbusMachine`) and
poller, so a simulated test exercises the controller link as a real test does: register map,
request batching, float decoding, commands written as coils or registers, polling. The
tests' controller peers are built on the same classes.

* `ControllerServer`: a pymodbus server (TCP, or RTU on a serial device such as one end of a
  pty pair) on an asyncio loop in a background thread, answering from a `RegisterSource`.
  Its datastore is pymodbus' SimDevice with the four tables apart (coils, discrete inputs,
  holding, input registers; 128 registers and 64 bits each, so an address beyond them gets
  pymodbus' own exception 2). The device's `action` callback, which pymodbus awaits on every
  access, puts the source's values into the registers before a read is answered and hands
  every write to the source. `stop` ends serving (the port is free, connections closed) and
  `serve_tcp` may serve again on the same port: a controller that goes away and comes back.
* `MachineRegisters`: the source for a live machine (`ServedMachine`) behind a register map.
* `DirectMachine`: a `ServedMachine` over a `TestingMachine` (the simulated one).
* `ModbusServedMachine`: the `TestingMachine` a simulated test reads with `[sim] controller =
  "modbus-tcp"`: opening it serves the simulated machine on a free 127.0.0.1 port (generic
  register map) and connects the appliance's Modbus client and poller to it; closing it
  closes both.

What it does not model: controller scan cycles, filtering, interlocks, a shared RS-485 line,
inter-message timing on the wire.
"""

from __future__ import annotations

import asyncio
import socket
import threading
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from hal.errors import HardwareConnectError
from hal.machine.base import MachineState, TestingMachine
from hal.machine.register_map import BIT_TABLES, COMMANDS, GENERIC_CONTROLLER, RegisterMap

REGISTERS_PER_TABLE = 128
BITS_PER_TABLE = 64
START_TIMEOUT_S = 10.0

_TABLE_OF_FUNCTION = {
    1: "coil",
    5: "coil",
    15: "coil",
    2: "discrete",
    3: "holding",
    6: "holding",
    16: "holding",
    22: "holding",
    23: "holding",
    4: "input",
}


class RegisterSource(Protocol):
    """What a `ControllerServer` answers from."""

    def image(self, table: str) -> Mapping[int, int | bool]:
        """The cells of `table` to serve now: {address: word or bit}; others keep their value."""

    def write(self, table: str, address: int, values: list[int] | list[bool]) -> int | None:
        """A client wrote `values` from `address`; an exception code refuses it (None: done)."""


class ControllerServer:
    """A pymodbus server answering from `source`, TCP or RTU, in a background thread.

    Args:
        source: the register source.
        unit: the device id it answers.
    """

    def __init__(self, source: RegisterSource, *, unit: int = 1) -> None:
        self.source = source
        self.unit = unit
        self.requests = 0
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="modbus-controller", daemon=True)
        self._thread.start()
        self._server: ModbusTcpServer | ModbusSerialServer | None = None

    def serve_tcp(self, port: int, host: str = "127.0.0.1") -> None:
        """Listen on host:port (returns once listening)."""
        self._call(self._start(lambda device: ModbusTcpServer(device, address=(host, port))))

    def serve_rtu(self, device: str, baud: int = 115200) -> None:
        """Serve Modbus RTU on a serial device (one end of a pty pair)."""
        self._call(
            self._start(
                lambda simdevice: ModbusSerialServer(
                    simdevice, port=device, baudrate=baud, parity="N", stopbits=1, bytesize=8
                )
            )
        )

    def stop(self) -> None:
        """Stop serving: the listener and every connection closed; may serve again after."""
        self._call(self._shutdown())

    def close(self) -> None:
        """Stop serving and end the thread; safe to call twice."""
        if self._loop.is_closed() or not self._thread.is_alive():
            return
        self.stop()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT_S)

    def __enter__(self) -> ControllerServer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    def _call(self, coroutine) -> None:
        asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(START_TIMEOUT_S)

    def _device(self) -> SimDevice:
        def bits() -> list[SimData]:
            return [SimData(address=0, count=BITS_PER_TABLE, values=False, datatype=DataType.BITS)]

        def registers() -> list[SimData]:
            return [SimData(address=0, count=REGISTERS_PER_TABLE, datatype=DataType.REGISTERS)]

        return SimDevice(
            id=self.unit,
            simdata=(bits(), bits(), registers(), registers()),
            action=self._action,
        )

    async def _start(self, make: Callable[[SimDevice], ModbusTcpServer | ModbusSerialServer]):
        if self._server is not None:
            raise RuntimeError("already serving")
        server = make(self._device())
        await server.serve_forever(background=True)
        self._server = server

    async def _shutdown(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        table = _TABLE_OF_FUNCTION[function_code]
        if values is not None:
            code = self.source.write(table, address, list(values))
            return ExcCodes(code) if code else None
        self.requests += 1
        cells = self.source.image(table)
        usable = len(registers) - 1
        if table in BIT_TABLES:
            # SimDevice keeps bits packed 16 to a register, bit 0 first.
            for bit_address, bit in cells.items():
                index, shift = divmod(bit_address, 16)
                index -= start_address
                if 0 <= index < usable:
                    word = registers[index] & ~(1 << shift)
                    registers[index] = word | (int(bool(bit)) << shift)
        else:
            for register_address, word in cells.items():
                index = register_address - start_address
                if 0 <= index < usable:
                    registers[index] = int(word)
        return None


class ServedMachine(Protocol):
    """A machine a `MachineRegisters` answers for."""

    def state(self) -> Mapping[str, float | bool]:
        """The quantities of the register map's reads now (crosshead_mm, speed_mm_min,
        force_n, running, encoder_counts)."""

    def start(self, speed_mm_min: float) -> None:
        """Start the crosshead at a speed."""

    def stop(self) -> None:
        """Stop the crosshead."""

    def return_to_start(self, speed_mm_min: float) -> None:
        """Drive the crosshead back to its start."""


class DirectMachine:
    """A `ServedMachine` over a testing machine (the simulated one, commands accepted)."""

    def __init__(self, machine: TestingMachine) -> None:
        self.machine = machine

    def state(self) -> Mapping[str, float | bool]:
        state = self.machine.read_state()
        return {
            "crosshead_mm": state.crosshead_mm,
            "speed_mm_min": state.speed_mm_min,
            "force_n": state.force_n,
            "running": state.running,
            "encoder_counts": state.encoder_counts or 0,
        }

    def start(self, speed_mm_min: float) -> None:
        self.machine.start(speed_mm_min)

    def stop(self) -> None:
        self.machine.stop()

    def return_to_start(self, speed_mm_min: float) -> None:
        self.machine.return_to_start(speed_mm_min)


class MachineRegisters:
    """A machine served through a register map: the `RegisterSource` of a live controller.

    Reads are the machine's state encoded by `register_map`; writes of the map's command
    coils or command registers and of the speed set point become the machine's commands (a
    start at the last set point, a stop, a return to the start), logged in the order they
    arrived.

    Args:
        register_map: the layout it serves.
        machine: the machine it answers for.
    """

    def __init__(self, register_map: RegisterMap, machine: ServedMachine) -> None:
        self.register_map = register_map
        self.machine = machine
        self._lock = threading.Lock()
        self._commands: list[tuple[str, float | bool]] = []
        self._holding: dict[int, int] = {}
        self.setpoint_mm_min = 0.0

    def commands(self) -> list[tuple[str, float | bool]]:
        """The commands and set points written so far, in order: (name, value)."""
        with self._lock:
            return list(self._commands)

    def image(self, table: str) -> Mapping[int, int | bool]:
        return self.register_map.register_image(self.machine.state())[table]

    def write(self, table: str, address: int, values: list[int] | list[bool]) -> int | None:
        entries = self.register_map.entries()
        if table == "coil":
            for offset, value in enumerate(values):
                for name in COMMANDS:
                    entry = entries.get(name)
                    if (
                        entry is not None
                        and entry.table == "coil"
                        and entry.address == address + offset
                    ):
                        if value:
                            self._command(name, True)
            return None
        if table != "holding":
            return int(ExcCodes.ILLEGAL_ADDRESS)
        for offset, word in enumerate(values):
            self._holding[address + offset] = int(word)
        written = range(address, address + len(values))
        setpoint = entries.get("speed_setpoint_mm_min")
        if setpoint is not None and setpoint.address in written and setpoint.end - 1 in written:
            words = [self._holding[a] for a in range(setpoint.address, setpoint.end)]
            self.setpoint_mm_min = float(setpoint.decode(words))
            with self._lock:
                self._commands.append(("speed_setpoint_mm_min", self.setpoint_mm_min))
        for name in COMMANDS:
            entry = entries.get(name)
            if entry is None or entry.table != "holding" or entry.address not in written:
                continue
            if entry.end - 1 not in written:
                continue
            words = [self._holding[a] for a in range(entry.address, entry.end)]
            if words == entry.command_words():
                self._command(name, entry.value)
        return None

    def _command(self, name: str, value: float | bool | None) -> None:
        with self._lock:
            self._commands.append((name, value))
        if name == "start":
            self.machine.start(self.setpoint_mm_min)
        elif name == "stop":
            self.machine.stop()
        else:
            self.machine.return_to_start(self.setpoint_mm_min)


class ModbusServedMachine:
    """A testing machine read over Modbus TCP on loopback from a server answering for it.

    Args:
        machine: the machine served (the simulated one).
        poll_rate_hz: the poller's rate (`appliance.devices.polled_machine.PolledMachine`).
        register_map: the layout served and read (the generic preset by default).
    """

    def __init__(
        self,
        machine: TestingMachine,
        *,
        poll_rate_hz: float = 100.0,
        register_map: RegisterMap = GENERIC_CONTROLLER,
    ) -> None:
        self.served = machine
        self.poll_rate_hz = poll_rate_hz
        self.register_map = register_map
        self.url = "modbus-tcp://127.0.0.1 (not serving)"
        self.registers = MachineRegisters(register_map, DirectMachine(machine))
        self._server: ControllerServer | None = None
        self._client: TestingMachine | None = None

    def open(self, timeout_s: float = 5.0) -> None:
        """Serve the machine on a free loopback port and connect the client to it.

        Raises HardwareConnectError when no port can be served or the client cannot connect.
        """
        from appliance.devices.polled_machine import PolledMachine
        from hal.registry import machine_from_url

        if self._client is not None:
            return
        self.served.open(timeout_s)
        server = ControllerServer(self.registers)
        try:
            port = _serve_on_a_free_port(server)
            self.url = f"modbus-tcp://127.0.0.1:{port}"
            client = PolledMachine(
                machine_from_url(self.url, register_map=self.register_map, accepts_commands=True),
                rate_hz=self.poll_rate_hz,
            )
            client.open(timeout_s)
        except BaseException:
            server.close()
            raise
        self._server, self._client = server, client

    def close(self) -> None:
        """Close the client, then the server; safe to call twice."""
        client, self._client = self._client, None
        server, self._server = self._server, None
        if client is not None:
            client.close()
        if server is not None:
            server.close()
        self.served.close()

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        return self._require().read_state(timeout_s)

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        self._require().start(speed_mm_min, timeout_s)

    def stop(self, timeout_s: float = 1.0) -> None:
        self._require().stop(timeout_s)

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        self._require().return_to_start(speed_mm_min, timeout_s)

    def statistics(self) -> dict[str, Any]:
        """The Modbus client's counters ({} when closed)."""
        return self._client.statistics() if self._client is not None else {}

    def _require(self) -> TestingMachine:
        if self._client is None:
            raise HardwareConnectError(f"{self.url}: not open")
        return self._client


def _serve_on_a_free_port(server: ControllerServer, attempts: int = 5) -> int:
    """Serve TCP on 127.0.0.1 on a port the kernel picks; a port taken between the pick
    and the bind is picked again."""
    failure: OSError | None = None
    for _ in range(attempts):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.bind(("127.0.0.1", 0))
            port = int(probe.getsockname()[1])
        try:
            server.serve_tcp(port)
            return port
        except OSError as exc:
            failure = exc
    raise HardwareConnectError(
        f"modbus-tcp://127.0.0.1: cannot serve the simulated machine: {failure}"
    )
