"""Benchmark of the Modbus machine client: state reads per second and read latency.

`run_machine_benchmark(out, as_json, url=None, duration_s=5.0)` (the CLI's `extensometer bench
machine`) reads the controller's state through `hal.machine.modbus.ModbusMachine` with the generic
register map (one request of 9 input registers per read) in two phases of `duration_s` each:

* **as fast as possible**: one `read_state` right after the other; the rate is what one
  client thread gets, the latency each call's duration (perf_counter around `read_state`,
  so it includes decoding and building the `MachineState`);
* **paced at 100 Hz**: a read every 10 ms on a fixed schedule, as the appliance's poller
  reads (appliance/devices/polled_machine.py); reported with the achieved rate and how many periods
  started late (more than one period behind the schedule).

The target: >= 100 state reads per second over TCP on loopback, with the p99 latency
reported. Failures are counted by kind (a failed read is not in the latency figures).

Without `url` the program starts its own controller: a separate Python process (so the
server does not share the client's interpreter lock) running a pymodbus TCP server on
127.0.0.1 at a free port, serving the appliance's simulated machine (`MachineWithSpecimen`, a steel
S355 flat specimen pulled at 5 mm/min) through the generic map. Like a controller's scan
cycle, a task on the server's loop refreshes the registers from the machine every 5 ms and
requests are answered from them; a request that arrives during a refresh (about 0.6 ms of
model computation, so roughly one in eight) waits for it, as it would behind a real
controller's cycle. With `url` it reads that controller (generic map) and starts nothing.

What it does not measure: a real controller's answer time, a network beyond loopback, RTU
(at 115200 baud the 9-register read takes about 2.7 ms on the wire alone), or the client
under the load of the measurement running beside it.
"""

from __future__ import annotations

import asyncio
import os
import platform
import sys
import time
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from appliance.bench.peer_process import free_loopback_port, percentiles_ms, start_peer, stop_peer

TARGET_RATE_HZ = 100.0
PACED_RATE_HZ = 100.0
READ_TIMEOUT_S = 1.0
CONTROLLER_CYCLE_S = 0.005
"""The simulated controller refreshes its registers from the machine this often."""
PULL_SPEED_MM_MIN = 5.0
SERVER_START_TIMEOUT_S = 30.0


def _phase(client: Any, duration_s: float, rate_hz: float | None) -> dict[str, Any]:
    """Read for `duration_s`: back to back (rate_hz None) or on a fixed schedule."""
    from hal.errors import HardwareError

    latencies: list[float] = []
    failures: Counter[str] = Counter()
    late = 0
    period = 1.0 / rate_hz if rate_hz else 0.0
    started = time.perf_counter()
    end = started + duration_s
    next_at = started
    while True:
        now = time.perf_counter()
        if rate_hz:
            if next_at >= end:
                break
            if now < next_at:
                time.sleep(next_at - now)
            elif now - next_at > period:
                late += 1
            next_at += period
        elif now >= end:
            break
        before = time.perf_counter()
        try:
            client.read_state(timeout_s=READ_TIMEOUT_S)
        except HardwareError as exc:
            failures[type(exc).__name__] += 1
            continue
        latencies.append(time.perf_counter() - before)
    elapsed = time.perf_counter() - started
    figures: dict[str, Any] = {
        "duration_s": elapsed,
        "reads": len(latencies),
        "rate_hz": len(latencies) / elapsed if elapsed > 0 else 0.0,
        "latency_ms": percentiles_ms(latencies),
        "failures": dict(failures),
    }
    if rate_hz:
        figures["requested_rate_hz"] = rate_hz
        figures["late_periods"] = late
    return figures


def measure_machine_client(url: str | None = None, duration_s: float = 5.0) -> dict[str, Any]:
    """Both phases against `url` (None: a simulated controller started here); the figures."""
    from hal.machine.modbus import ModbusMachine

    load = os.getloadavg()[0]
    server = None
    if url is None:
        port = free_loopback_port()
        server = start_peer(
            "appliance.bench.machine_client", ["serve", str(port)], "the simulated controller"
        )
        target = f"modbus-tcp://127.0.0.1:{port}?unit=1"
    else:
        target = url
    client = ModbusMachine(target)
    try:
        client.open(timeout_s=5.0)
        for _ in range(50):
            client.read_state(timeout_s=READ_TIMEOUT_S)
        fast = _phase(client, duration_s, None)
        paced = _phase(client, duration_s, PACED_RATE_HZ)
        statistics = client.statistics()
    finally:
        client.close()
        if server is not None:
            stop_peer(server, "the simulated controller", timeout_s=30.0)
    met = fast["rate_hz"] >= TARGET_RATE_HZ and paced["rate_hz"] >= 0.99 * PACED_RATE_HZ
    return {
        "benchmark": "machine_client",
        "target": f">= {TARGET_RATE_HZ:g} state reads/s over TCP on loopback, p99 reported",
        "verdict": "met" if met else "missed",
        "setup": {
            "url": target,
            "controller": "simulated (own process, MachineWithSpecimen, generic map)"
            if url is None
            else "given",
            "register_map": "generic (one request: input 0..8)",
            "read_timeout_s": READ_TIMEOUT_S,
            "phase_duration_s": duration_s,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average_1min": load,
        },
        "as_fast_as_possible": fast,
        "paced": paced,
        "client_statistics": statistics,
    }


def _row(name: str, phase: Mapping[str, Any]) -> str:
    latency = phase["latency_ms"]

    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:.3f}"

    failures = sum(phase["failures"].values())
    return (
        f"| {name} | {phase['rate_hz']:.1f} | {cell(latency['p50'])} | {cell(latency['p99'])} | "
        f"{cell(latency['max'])} | {phase['reads']} | {failures} |"
    )


def format_table(figures: Mapping[str, Any]) -> str:
    """The figures as a Markdown table."""
    setup = figures["setup"]
    paced = figures["paced"]
    return "\n".join(
        [
            f"Machine client over {setup['url']} ({setup['controller']}), {setup['cpus']} CPUs, "
            f"load average {setup['load_average_1min']:.2f} before the run; "
            f"target: {figures['target']} -> {figures['verdict']}",
            "",
            "| phase | reads/s | p50 ms | p99 ms | max ms | reads | failures |",
            "|---|---|---|---|---|---|---|",
            _row("as fast as possible", figures["as_fast_as_possible"]),
            _row(f"paced at {paced['requested_rate_hz']:g} Hz", paced),
            "",
            f"paced: {paced['late_periods']} periods started late; failures by kind: "
            f"{figures['as_fast_as_possible']['failures'] or 'none'} (fast), "
            f"{paced['failures'] or 'none'} (paced)",
        ]
    )


def run_machine_benchmark(
    out: Path | None, as_json: bool, url: str | None = None, duration_s: float = 5.0
) -> int:
    """Entry point of `extensometer bench machine`; prints the figures,
    writes its report into the directory `out` (when given).

    Returns the exit status (0: measured, whether or not the target was met).
    """
    from appliance.bench.results import emit_figures

    figures = measure_machine_client(url, duration_s)
    emit_figures(
        "machine",
        "Reading the machine's state over Modbus TCP",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0


def _serve(port: int) -> None:
    """The simulated controller (its own process): serve until a line or EOF on stdin."""
    asyncio.run(_serve_async(port))


async def _serve_async(port: int) -> None:
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    from appliance.sim.bar import BarModel
    from appliance.sim.machine import MachineWithSpecimen
    from appliance.sim.materials import ElasticPlastic
    from appliance.sim.specimen import Specimen
    from hal.machine.register_map import GENERIC_CONTROLLER

    machine = MachineWithSpecimen(BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355()))
    started = time.monotonic()
    machine.start(PULL_SPEED_MM_MIN, 0.0)
    image: dict[int, int | bool] = {}

    def refresh() -> None:
        state = machine.state(time.monotonic() - started)
        values = {
            "crosshead_mm": state.crosshead_mm,
            "speed_mm_min": state.speed_mm_min,
            "force_n": state.force_n,
            "running": state.running,
            "encoder_counts": state.encoder_counts or 0,
        }
        image.update(GENERIC_CONTROLLER.register_image(values)["input"])

    async def scan() -> None:
        next_at = time.monotonic()
        while True:
            refresh()
            next_at += CONTROLLER_CYCLE_S
            await asyncio.sleep(max(next_at - time.monotonic(), 0.0))

    refresh()
    scanning = asyncio.create_task(scan())

    async def action(function_code, start_address, address, count, registers, values):
        if function_code == 4 and values is None:
            for register_address, word in image.items():
                index = register_address - start_address
                if 0 <= index < len(registers) - 1:
                    registers[index] = int(word)
        return None

    def block(kind: DataType) -> list[SimData]:
        if kind is DataType.BITS:
            return [SimData(address=0, count=16, values=False, datatype=kind)]
        return [SimData(address=0, count=16, datatype=kind)]

    device = SimDevice(
        id=1,
        simdata=(
            block(DataType.BITS),
            block(DataType.BITS),
            block(DataType.REGISTERS),
            block(DataType.REGISTERS),
        ),
        action=action,
    )
    server = ModbusTcpServer(device, address=("127.0.0.1", port))
    await server.serve_forever(background=True)
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
    scanning.cancel()
    await server.shutdown()


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "serve":
        _serve(int(sys.argv[2]))
    else:
        sys.exit(
            "usage: python -m appliance.bench.machine_client serve PORT (the benchmark's server)"
        )
