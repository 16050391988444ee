"""Test recordings: one MCAP file per test, written live, read back exactly, measured again.

What lives here: the recording format (channels, schemas, encodings, the format version;
`format`), the writer that follows a test as an output on its own thread (`writer`), the
reader that reads a file front to back up to any damage (`reader`) and reads older format
versions in the current names (`migration`), the replay that measures a recording again with
the live loop's per-frame code (`replay`), the summary `extensometer info` prints (`info`),
and the retention rule of the service's state directory (`retention`).

May import: `appliance.run`, `appliance.measure`, `appliance.config`, `appliance.errors`,
`hal` data types. Not the live outputs or the simulator.
"""
