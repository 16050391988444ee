"""ISO 9513 class from bias errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.run.iso9513 import CLASSES, best_class, class_named


def test_limits_are_the_larger_of_relative_and_absolute():
    class_05 = CLASSES[1]
    assert class_05.limit_um(np.array([100.0]))[0] == 1.5
    assert class_05.limit_um(np.array([1000.0]))[0] == pytest.approx(5.0)


@pytest.mark.parametrize(
    ("error_um", "true_um", "expected"),
    [
        (0.5, 50.0, "0.2"),
        (1.0, 50.0, "0.5"),
        (3.0, 1000.0, "0.5"),
        (2.5, 100.0, "1"),
        (5.0, 100.0, "2"),
        (7.0, 100.0, None),
        (15.0, 1000.0, "2"),
    ],
)
def test_best_class(error_um, true_um, expected):
    assert best_class([true_um + error_um], [true_um]) == expected


def test_worst_reading_decides_and_nan_fails():
    assert best_class([10.1, 20.0 + 2.0], [10.0, 20.0]) == "1"
    assert best_class([math.nan], [1.0]) is None
    assert best_class([], []) is None
    with pytest.raises(ValueError):
        best_class([1.0], [1.0, 2.0])


def test_every_class_has_its_resolution_and_gauge_length_limits():
    table = {
        c.name: (c.resolution_relative, c.resolution_um, c.gauge_length_relative) for c in CLASSES
    }
    assert table == {
        "0.2": (0.001, 0.2, 0.002),
        "0.5": (0.0025, 0.5, 0.005),
        "1": (0.005, 1.0, 0.01),
        "2": (0.01, 2.0, 0.02),
    }
    class_05 = class_named("0.5")
    assert class_05.resolution_limit_um(np.array([100.0]))[0] == 0.5
    assert class_05.resolution_limit_um(np.array([1000.0]))[0] == pytest.approx(2.5)


def test_classes_are_named_as_the_standard_writes_them():
    assert class_named("1.0") is class_named("1")
    with pytest.raises(ValueError, match="0.3"):
        class_named("0.3")
