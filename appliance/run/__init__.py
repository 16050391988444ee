"""One test's run: the measurement loop, its states, its outputs and its results.

What lives here: the measurement loop on its acquisition, tracking and publishing threads
(`loop`), the run states and their transitions (`state`), the seam every output of a test
implements (`outputs`), the summary of a run (`summary`), the strain CSV file (`strain_file`),
room on disk (`disk_space`), dropped-frame warnings (`drops`), the ISO 9513 classes the
summary grades against (`iso9513`), the measurement in the specimen plane through a camera
calibration and its out-of-plane bound (`object_plane`), and ISO 9513 verification against a
calibrator: the grading (`verification`), a lab's readings file (`verification_readings`), the
calibrator's targets measured in frames (`calibrator_measurement`) and the report
(`verification_report`).

May import: `appliance.measure`, `appliance.optics`, `appliance.config`, `appliance.errors`,
`hal` protocols.
Not the planner, the devices' glue, the recording or the live outputs (they plug in as
outputs and listeners).
"""
