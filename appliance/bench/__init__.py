"""Benchmarks of the measurement core: programs that measure, print figures and write reports.

Targets are checked here, never in timed tests. Every figure is measured in the run that
reports it; ratios compare methods timed in the same run on the same computer.
"""
