"""A short simulated test measured through a Rerun viewer, in this process or as a child process.

`measure(output, frames)` runs the real measurement loop (simulated camera and frame, a speckle
image stretched at a constant rate, two axial marks of two points, a transverse gauge) with
`output` as its output, calling `begin`, every sample and `end` as the runner does, and
returns the samples and the loop's result. `Recorder` is an output that keeps what it gets,
to replay into a viewer by hand.

As a program it is the appliance side of the remote monitoring test: rerun 0.41's gRPC server
lets go of a connected viewer only when the serving process ends, so the served tests run in a
process of their own:

    python -m tests.system.viewer_sender --serve 127.0.0.1:PORT --tests 2 --out DIR

It starts one `RerunViewer` (and so its gRPC server), prints "serving URL", then runs one test
per line read on stdin (test id and recording "<prefix>-<k>"), writes the strains of test k
to DIR/test-<k>.json and prints "done k"; at the end of stdin it closes the viewer and exits.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from appliance.config import Config, RerunConfig
from appliance.dic import synthetic
from appliance.live.viewer import RerunViewer
from appliance.measure.frame_measurer import StopCriteria, StrainSample
from appliance.measure.gauges import Calibration, Gauge, StrainGauges, StrainGaugesLayout
from appliance.measure.tracking import MarkTracker, TrackerSettings
from appliance.run.loop import LoopResult, MeasurementLoop
from appliance.run.outputs import RunFacts
from hal.camera.base import Region, TriggerInfo, TriggerMode
from hal.camera.sim import SimCamera
from hal.clock import SimClock
from hal.machine.base import MachineState
from hal.machine.sim import SimMachine

HEIGHT, WIDTH = 320, 200
POINTS = np.array(
    [[100.0, 100.0], [108.0, 100.0], [100.0, 220.0], [108.0, 220.0], [60.0, 160.0], [140.0, 160.0]]
)
MARKS = ((0, 1), (2, 3), (4,), (5,))
LAYOUT = StrainGaugesLayout(axial=Gauge((0, 1), (2, 3)), transverse=Gauge((4,), (5,)))
SCALE_MM_PER_PX = 0.1
STRAIN_RATE = 0.02
"""Engineering strain per second."""
FRAME_RATE_HZ = 10.0
EPOCH_OFFSET_NS = 1_750_000_000_000_000_000
FORCE_N_PER_STRAIN = 20_000.0


class StretchingScene:
    """A speckle image stretched along y about the specimen centre at a constant strain rate."""

    sensor_width = WIDTH
    sensor_height = HEIGHT

    def __init__(self) -> None:
        self.pattern = synthetic.dense_speckle(WIDTH, HEIGHT, seed=7, radius=2.5)

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        strain = STRAIN_RATE * 0.5 * (start_s + stop_s)
        mapping = synthetic.UniaxialStretch(1 + strain, axis="y", xc=100.0, yc=160.0)
        return synthetic.render(self.pattern, HEIGHT, WIDTH, mapping), {"strain": strain}


class LinearMachine:
    """A crosshead at constant speed and a force proportional to the scene's strain."""

    def state(self, t_s: float) -> MachineState:
        return MachineState(
            crosshead_mm=0.5 * t_s,
            speed_mm_min=30.0,
            force_n=FORCE_N_PER_STRAIN * STRAIN_RATE * t_s,
            running=True,
            timestamp_ns=round(t_s * 1e9),
        )

    def start(self, speed_mm_min: float, t_s: float) -> None:
        pass

    def stop(self, t_s: float) -> None:
        pass

    def return_to_start(self, speed_mm_min: float, t_s: float) -> None:
        pass


class Recorder:
    """An output that keeps the facts, the samples and the result of a test."""

    def __init__(self) -> None:
        self.facts: RunFacts | None = None
        self.samples: list[StrainSample] = []
        self.result: LoopResult | None = None

    def begin(self, facts: RunFacts) -> None:
        self.facts = facts

    def __call__(self, sample: StrainSample) -> None:
        self.samples.append(sample)

    def end(self, result: LoopResult) -> None:
        self.result = result


def record(frames: int, test_id: str = "recorded") -> Recorder:
    """A simulated test of `frames` samples, recorded."""
    recorder = Recorder()
    measure(recorder, frames, test_id)
    return recorder


def measure(output, frames: int, test_id: str) -> tuple[list[StrainSample], LoopResult]:
    """Run a simulated test `test_id` of `frames` samples through `output`; (samples, result)."""
    clock = SimClock()
    camera = SimCamera(
        "sim://camera", scene=StretchingScene(), clock=clock, read_noise=0.0, electrons_per_grey=0.0
    )
    camera.open()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=FRAME_RATE_HZ, exposure_us=100.0))
    machine = SimMachine("sim://machine", machine=LinearMachine(), clock=clock)
    machine.open()
    samples: list[StrainSample] = []
    calibration = Calibration(SCALE_MM_PER_PX)

    def setup(reference):
        tracker = MarkTracker(reference.image, POINTS, MARKS, TrackerSettings(subset_px=31))
        gauges = StrainGauges(LAYOUT.axial, POINTS, calibration, LAYOUT.transverse)
        output.begin(
            RunFacts(
                config=Config(),
                reference=reference,
                points=POINTS,
                marks=MARKS,
                layout=LAYOUT,
                calibration=calibration,
                gauge_length_mm=gauges.gauge_length_mm,
                epoch_offset_ns=EPOCH_OFFSET_NS,
                devices={"camera": "sim://camera", "machine": "sim://machine"},
                facts={"test_id": test_id, "scene": "uniaxial stretch"},
            )
        )
        return tracker, gauges

    loop = MeasurementLoop(
        camera, machine, setup, sinks=[samples.append, output], block_when_full=True
    )
    result = loop.run(StopCriteria(until_break=False, max_frames=frames))
    output.end(result)
    return samples, result


def renumbered(sample: StrainSample, index: int, timestamp_ns: int) -> StrainSample:
    """A copy of `sample` as sample `index`, exposed at `timestamp_ns` (device time)."""
    shift_s = (timestamp_ns - sample.timestamp_ns) * 1e-9
    return dataclasses.replace(
        sample, index=index, timestamp_ns=timestamp_ns, time_s=sample.time_s + shift_s
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--serve", required=True)
    parser.add_argument("--tests", type=int, default=2)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--prefix", default="served")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    viewer = RerunViewer(RerunConfig(serve=args.serve, image_rate_hz=5.0, queue_size=1000))
    viewer.start()
    try:
        print(f"serving {viewer.service.url}", flush=True)
        for k in range(args.tests):
            if not sys.stdin.readline():
                break
            samples, result = measure(viewer, args.frames, f"{args.prefix}-{k}")
            report = {
                "strains": {
                    str(s.index): s.reading.engineering_strain
                    for s in samples
                    if math.isfinite(s.reading.engineering_strain)
                },
                "exit_status": result.exit_status,
                "shown": viewer.samples_shown,
                "dropped": viewer.samples_dropped,
                "problem": viewer.problem,
            }
            (args.out / f"test-{k}.json").write_text(json.dumps(report))
            print(f"done {k}", flush=True)
        sys.stdin.read()
    finally:
        viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
