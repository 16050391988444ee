"""Optics of the measurement: camera model, calibration, pixels to millimetres on the specimen
plane."""
