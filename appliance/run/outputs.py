"""The seam between a test and what follows it: outputs, their facts, and the run's hooks.

An output (the MCAP recorder, the Rerun viewer) follows one test:

    begin(facts)      once, after the reference frame is taken and the marks are placed
    output(sample)    for every sample, in order, on the loop's publishing thread
    end(result)       once, after the loop has ended (also after a fault or an abort)
    stats()           after `end`: figures the output adds to the test's summary

`RunFacts` holds everything fixed for the whole test: the configuration in force, the
reference frame, the points and how they form gauge marks, the calibration, the device
identities, and the mapping from device time to UNIX time.

`RunHooks` is everything outside the runner that follows or drives one test, as one value:
outputs, the samples' immediate sinks (Modbus registers, watchdog), and the listeners of run
states, of the loop and of device events.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from appliance.config import Config
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.gauges import Calibration, StrainGaugesLayout
from appliance.run.loop import DeviceEvent, LoopResult, MeasurementLoop
from appliance.run.state import Transition
from hal.camera.base import Frame


@dataclass(frozen=True)
class RunFacts:
    """The facts of one test, fixed from its reference frame on.

    Attributes:
        config: the configuration in force (after command-line overrides).
        reference: the reference frame (strain zero).
        points: (n, 2) positions of the tracked points in the reference frame, px.
        marks: groups of point indices tracked together (the tracker's marks).
        layout: which points form the axial (and transverse) gauge.
        calibration: px -> mm in the object plane.
        gauge_length_mm: the original axial gauge length L0, mm.
        epoch_offset_ns: add to a device timestamp to get UNIX time, ns (measured when the
            reference frame was delivered).
        devices: identities of the devices and software, name -> text (camera, machine,
            software version).
        facts: further facts worth keeping (exposure plan, material of a simulation).
    """

    config: Config
    reference: Frame
    points: np.ndarray
    marks: tuple[tuple[int, ...], ...]
    layout: StrainGaugesLayout
    calibration: Calibration
    gauge_length_mm: float
    epoch_offset_ns: int
    devices: Mapping[str, str] = field(default_factory=dict)
    facts: Mapping[str, object] = field(default_factory=dict)

    def unix_time_ns(self, device_ns: int) -> int:
        """UNIX time of a device timestamp, ns."""
        return int(device_ns) + self.epoch_offset_ns


@runtime_checkable
class RunOutput(Protocol):
    """An output that follows one test."""

    def begin(self, facts: RunFacts) -> None:
        """The test has its reference; nothing has been measured yet."""

    def __call__(self, sample: StrainSample) -> None:
        """The next sample (publishing thread)."""

    def end(self, result: LoopResult) -> None:
        """The test is over; `result` says how it ended. Close files and connections."""

    def stats(self) -> dict[str, Any]:
        """Figures for the test's summary (after `end`; {} when the output has none)."""


@dataclass(frozen=True)
class RunHooks:
    """What follows and drives one test from outside the runner.

    Attributes:
        outputs: outputs following the test besides the runner's own (a viewer).
        immediate_sinks: called with every sample on the tracking thread as soon as it is
            measured (Modbus registers, watchdog): fast, non-blocking work only.
        on_transition: called at every change of the run state.
        on_loop: called with the measurement loop before it runs (to stop or zero it from
            another thread).
        device_listeners: called with every `DeviceEvent` (a camera or the machine lost or
            back), on the acquisition thread.
        on_warning: called with a warning about the running test, one line (frames dropped:
            `appliance.run.drops`), on the publishing thread; the recording logs it as well.
        on_alive: called periodically while the measurement loop is in control, never
            while one of its calls hangs (`MeasurementLoop`'s liveness listeners: the
            service's watchdog); fast, non-blocking work only.
        on_results: called once the test's results are computed, with the summary's
            `results` object (JSON-ready: `standard`, and by symbol `value`, `unit`, ...),
            before `outputs` end (so a viewer can show them); not called when the results
            could not be computed.
    """

    outputs: Sequence[RunOutput] = ()
    immediate_sinks: Sequence[Callable[[StrainSample], None]] = ()
    on_transition: Callable[[Transition], None] | None = None
    on_loop: Callable[[MeasurementLoop], None] | None = None
    device_listeners: Sequence[Callable[[DeviceEvent], None]] = ()
    on_warning: Callable[[str], None] | None = None
    on_alive: Callable[[], None] | None = None
    on_results: Callable[[Mapping[str, Any]], None] | None = None
