"""The operator's view of a running test on a terminal: one self-rewriting line, and notes.

`ProgressLine` shows the latest sample (time, sample index, strain, force, validity) on one
line that rewrites itself, and puts device events and re-plannings on lines of their own
above it, so they stay readable in the scroll-back.
"""

from __future__ import annotations

from typing import TextIO

from appliance.measure.frame_measurer import StrainSample
from appliance.run.loop import DeviceEvent


class ProgressLine:
    """A test's progress on a terminal stream.

    Args:
        stream: the terminal (stderr, typically).
    """

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def __call__(self, sample: StrainSample) -> None:
        """Show a sample (a sink of the loop's publishing thread)."""
        r = sample.reading
        machine = sample.machine
        force = f" force {machine.force_n:9.1f} N" if machine is not None else ""
        flag = "valid" if sample.data_valid else "INVALID"
        self.stream.write(
            f"\r  t {sample.time_s:7.2f} s  frame {sample.index:6d}  strain "
            f"{r.engineering_strain * 100:9.3f} %{force}  {flag}"
        )
        self.stream.flush()

    def device_event(self, event: DeviceEvent) -> None:
        """A device lost or back, on a line of its own (the repeated "waiting" is not shown)."""
        if event.kind != "waiting":
            self.note(f"{event.device} {event.kind}: {event.text}")

    def note(self, text: str) -> None:
        """One line of its own above the progress line."""
        self.stream.write(f"\n  {text}\n")
        self.stream.flush()

    def close(self) -> None:
        """End the progress line."""
        self.stream.write("\n")
        self.stream.flush()
