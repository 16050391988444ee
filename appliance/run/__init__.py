"""One test's run: the measurement loop, its states, its outputs and its results.

What lives here: the measurement loop on its acquisition, tracking and publishing threads
(`loop`), the run states and their transitions (`state`), the seam every output of a test
implements (`outputs`), the summary of a run (`summary`), the strain CSV file (`strain_file`),
room on disk (`disk_space`), dropped-frame warnings (`drops`) and the ISO 9513 classes the
summary grades against (`iso9513`).

May import: `appliance.measure`, `appliance.config`, `appliance.errors`, `hal` protocols.
Not the planner, the devices' glue, the recording or the live outputs (they plug in as
outputs and listeners).
"""
