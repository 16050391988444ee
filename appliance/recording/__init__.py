"""Test recordings: one MCAP file per test, written live and read back exactly.

What lives here: the recording format (channels, schemas, encodings, the format version;
`format`), the writer that follows a test as an output on its own thread (`writer`), the
reader that reads a file front to back up to any damage and migrates older formats
(`reader`), and the summary `extensometer info` prints (`info`).

May import: `appliance.run`, `appliance.measure`, `appliance.config`, `appliance.errors`,
`hal` data types. Not the live outputs or the simulator.
"""
