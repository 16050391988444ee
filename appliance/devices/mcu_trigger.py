"""The trigger microcontroller driving the simulated camera: real firmware, simulated optics.

A simulated test can have its exposures timed by the real trigger microcontroller
(`[trigger] url`, a serial port or pyserial URL; in the tests the firmware under simavr): the
trigger plan is sent to the firmware (`firmware_bridge.link.McuLink`), and every TRIGGER it
reports becomes an edge on the simulated camera's trigger input, at the trigger's host time
from the link's clock sync, expressed on the simulation clock. The simulated world must then
run in real time (`[sim] realtime = true`), since the firmware's ticks follow wall time.

`McuTriggerLine` is that camera input: `next_edge_s` waits for the next TRIGGER (the camera's
fetch timeout bounds the wait) and keeps every event it consumed (`events`) so a test can
match frames to triggers by sequence. A TRIGGER the link reports without a clock fit yet is
skipped (its time is unknown) and counted. A BOOT during the test (the microcontroller reset:
its trigger plan and clock are gone, no further pulse comes) raises `HardwareFault` naming
the reset's cause (`restarted`), so the test ends as a fault that says why the frames stopped.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from appliance.errors import InputError
from appliance.plan.trigger_plan import TriggerPlan
from firmware_bridge.link import BootEvent, FirmwareError, McuLink, TriggerEvent
from firmware_bridge.messages import TriggerSource
from hal.errors import HardwareFault


class McuTriggerLine:
    """The real microcontroller's trigger as the appliance drives it: the plan sent and armed
    (`start`), re-timed (`retime`), disarmed (`stop`); and, in a simulated test, the
    simulated camera's trigger input fed by its TRIGGER events (`next_edge_s`). A real camera
    on its output reads the events through `appliance.devices.trigger_stamping` instead.

    Args:
        link: a connected link.
        sim_s_of_host_ns: host monotonic ns -> simulation time, s; None with a real camera
            (then `next_edge_s` is not used).
        wait_s: longest wait for one edge.
    """

    def __init__(
        self,
        link: McuLink,
        sim_s_of_host_ns: Callable[[int], float] | None = None,
        *,
        wait_s: float = 2.0,
    ) -> None:
        self.link = link
        self.sim_s_of_host_ns = sim_s_of_host_ns
        self.wait_s = wait_s
        self.events: list[TriggerEvent] = []
        self.unstamped = 0
        self._released = False
        self._armed_ns: int | None = None

    def start(self, plan: TriggerPlan, *, start_tick: int = 0) -> None:
        """Send the plan to the firmware and arm it; the first pulse at `start_tick` (0 = as
        soon as armed)."""
        if plan.source == "encoder":
            source, period, divisor = TriggerSource.ENCODER, 0, plan.encoder_divisor
        else:
            source, period, divisor = TriggerSource.PERIOD, plan.period_ticks, 1
        self._armed_ns = time.monotonic_ns()
        self.link.configure(source, plan.pulse_width_ticks, period, divisor, start_tick=start_tick)
        self.link.arm()

    def retime(self, plan: TriggerPlan) -> None:
        """Change the armed trigger's period or encoder divisor (the firmware's RETIME): the
        sequence numbers continue. Raises HardwareFault when the firmware refuses it or the
        link fails."""
        try:
            if plan.source == "encoder":
                self.link.retime(encoder_divisor=plan.encoder_divisor)
            else:
                self.link.retime(period_ticks=plan.period_ticks)
        except FirmwareError as exc:
            raise HardwareFault(f"{self.link.url}: RETIME: {exc}") from None

    def stop(self) -> None:
        """Disarm the firmware (errors of a link already gone are left to the caller)."""
        self.link.disarm()

    def release(self) -> None:
        """Disarm the firmware if the link still answers, and close the link; idempotent. The
        events consumed stay readable."""
        if self._released:
            return
        self._released = True
        try:
            self.stop()
        except FirmwareError:
            pass
        self.link.close()

    def next_edge_s(self, after_s: float) -> float | None:
        """Simulation time of the next TRIGGER after `after_s`; None when none comes within
        `wait_s`. Raises RuntimeError without a simulation clock."""
        if self.sim_s_of_host_ns is None:
            raise RuntimeError("next_edge_s: this trigger line drives a real camera")
        deadline = time.monotonic() + self.wait_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            event = self.link.next_event(remaining)
            if self.reset_under_test(event):
                raise self.restarted(event)
            if not isinstance(event, TriggerEvent):
                continue
            if event.host_time_ns is None:
                self.unstamped += 1
                continue
            self.events.append(event)
            edge = self.sim_s_of_host_ns(event.host_time_ns)
            if edge > after_s:
                return edge

    def reset_under_test(self, event: object) -> bool:
        """Whether `event` is a BOOT received after the plan was sent (`start`): the
        microcontroller reset under the test (the BOOT of its power-on is not)."""
        armed_ns = self._armed_ns
        return (
            isinstance(event, BootEvent) and armed_ns is not None and event.received_ns > armed_ns
        )

    def restarted(self, boot: BootEvent) -> HardwareFault:
        """The error of a test whose microcontroller reset under it."""
        cause = getattr(boot.cause, "name", boot.cause)
        return HardwareFault(
            f"[trigger] url: {self.link.url}: the trigger microcontroller restarted (reset "
            f"cause {cause}); its trigger plan is gone and no further trigger comes"
        )


def connect_trigger_line(
    url: str, sim_s_of_host_ns: Callable[[int], float] | None = None
) -> McuTriggerLine:
    """Connect to the trigger microcontroller at `url` (`[trigger] url`) and shake hands.

    Args:
        url: serial device or pyserial URL.
        sim_s_of_host_ns: as `McuTriggerLine`'s: the simulation clock of a simulated camera
            the line drives; None for a real camera on its output.

    Raises:
        InputError: naming `[trigger] url` when the link cannot be opened or the firmware
            does not speak this host's protocol.
    """
    try:
        link = McuLink(url)
        try:
            link.connect()
        except BaseException:
            link.close()
            raise
    except FirmwareError as exc:
        raise InputError(f"[trigger] url: {url}: {exc}") from None
    return McuTriggerLine(link, sim_s_of_host_ns)
