"""Measurement core: digital image correlation on numpy arrays, with no I/O.

Integer-pixel search (ZNCC, or LPQ histograms compared by chi-square), then IC-GN subpixel
refinement with a first-order shape function on a bicubic B-spline interpolant
(`correlation.Correlator` joins them); seed-and-propagate for displacement fields larger than
any search window (`propagation`). Synthetic speckle images with exact ground truth live here
too (`synthetic`, `blur`), so the simulated camera and the benchmarks render what the tracker
is tested on.

This package imports nothing else from the project (an import-linter contract checks it).
"""
