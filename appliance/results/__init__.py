"""A test's results and the report a person reads.

From the strain series, the machine's force and the specimen's original cross-section
(`[specimen]`): for metals the ISO 6892-1 results (`metals`: modulus, Rp0.2, ReH/ReL, Rm, Ag,
A), for rubber the ISO 37 results (`rubber`: TS, Eb, stresses at 100/200/300 %), each saying
which samples it used or why it was not determined (`result`). The series of one test
(`series`), its plots (`plots`), the HTML page (`report_page`) and the output that follows a
test, computes the results for its summary and writes `report.html` (`report_output`).

May import `run` (the outputs seam), `measure`, `config`, `errors` and `hal` data types; never
the simulated world: a simulated test's truth reaches the report only as a number to score
against, handed in by the composition.
"""
