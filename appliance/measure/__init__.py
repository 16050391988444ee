"""Measuring a test frame by frame: gauge marks tracked over time, and strain from them.

What lives here: the mark tracker that follows each gauge mark through a test with reference
updates (`tracking`), the gauges that turn tracked points into strain (`gauges`), the
per-frame measurer shared by the live loop and the replay (`frame_measurer`: one frame in,
one `StrainSample` out, with validity and the stop criteria), and the windows of a frame
that tracking reads (`frame_windows`).

May import: `appliance.dic`, `appliance.errors`, `hal` protocols and data types. Nothing
here knows about devices, configuration files, threads or outputs.
"""
