"""One result of a test, determined from named samples or not determined for a stated reason.

A `Result` is either a number with its unit and the samples it was taken from (the first and
last sample index used, and a sentence saying how), or no number with the reason. `TestResults`
is a test's results under one standard, as the summary's `results` object:

    {"standard": "ISO 6892-1", "cross_section_mm2": 25.0,
     "Rp0.2": {"name": ..., "value": 355.1, "unit": "MPa", "samples": [212, 213],
               "basis": "...", "not_determined": null}, ...}

Its `str()` is the line the printed summary shows: the main results, `-` for those not
determined.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Result:
    """One result.

    Attributes:
        symbol: the standard's symbol (`Rp0.2`, `Rm`, `E`, `TS`, `S100`).
        name: what it is, in words.
        unit: `MPa`, `GPa` or `%`.
        value: the result, in `unit`; None when not determined.
        samples: (first, last) sample index the value was taken from; None when not determined.
        basis: how the value was taken from those samples (fit range, interpolation).
        reason: why it was not determined (None when it was).
        at_sample: the sample index whose strain the result lies at on the curve (ReL: its
            lowest-stress sample; an interpolated result: the later sample); None when not
            determined.
    """

    symbol: str
    name: str
    unit: str
    value: float | None = None
    samples: tuple[int, int] | None = None
    basis: str = ""
    reason: str | None = None
    at_sample: int | None = None

    @classmethod
    def determined(
        cls,
        symbol: str,
        name: str,
        unit: str,
        value: float,
        samples: tuple[int, int],
        basis: str,
        *,
        at_sample: int | None = None,
    ) -> Result:
        """A result taken from samples `samples[0]` to `samples[1]`, lying at the strain of
        sample `at_sample` (default `samples[1]`); NaN is refused."""
        if not math.isfinite(value):
            raise ValueError(f"{symbol}: a result must be a finite number, got {value}")
        first, last = int(samples[0]), int(samples[1])
        at = last if at_sample is None else int(at_sample)
        return cls(symbol, name, unit, float(value), (first, last), basis, None, at)

    @classmethod
    def not_determined(cls, symbol: str, name: str, unit: str, reason: str) -> Result:
        """A result that could not be determined, and why."""
        return cls(symbol, name, unit, reason=reason)

    @property
    def is_determined(self) -> bool:
        """Whether there is a value."""
        return self.value is not None

    def text(self) -> str:
        """The value with its unit (`355.1 MPa`), or `not determined`."""
        if self.value is None:
            return "not determined"
        return f"{self.value:.5g} {self.unit}"

    def as_dict(self) -> dict[str, Any]:
        """The result as a JSON-ready dictionary."""
        return {
            "name": self.name,
            "value": self.value,
            "unit": self.unit,
            "samples": list(self.samples) if self.samples is not None else None,
            "basis": self.basis,
            "not_determined": self.reason,
        }


@dataclass(frozen=True)
class TestResults:
    """A test's results under one standard.

    Attributes:
        standard: `ISO 6892-1` or `ISO 37`.
        cross_section_mm2: the original cross-section S0 the stresses are taken with, mm^2
            (None: not configured).
        results: the results, in the standard's order.
        main: the symbols the printed summary shows.
    """

    standard: str
    cross_section_mm2: float | None
    results: Sequence[Result]
    main: tuple[str, ...] = ()

    def __getitem__(self, symbol: str) -> Result:
        for result in self.results:
            if result.symbol == symbol:
                return result
        raise KeyError(symbol)

    def as_dict(self) -> dict[str, Any]:
        """The summary's `results` object."""
        return {
            "standard": self.standard,
            "cross_section_mm2": self.cross_section_mm2,
            **{r.symbol: r.as_dict() for r in self.results},
        }

    def line(self) -> str:
        """The main results on one line: `ISO 6892-1: Rp0.2 355.1 MPa, Rm 510 MPa, ...`."""
        shown = [self[symbol] for symbol in self.main]
        parts = [f"{r.symbol} {r.text() if r.is_determined else '-'}" for r in shown]
        return f"{self.standard}: {', '.join(parts)}"


class ResultsObject(dict):
    """The summary's `results` object: a plain dictionary in JSON, one line when printed
    (`str`), as the printed summary shows every value by its text.

    Args:
        document: the JSON object (`TestResults.as_dict`).
        line: what `str` gives (`TestResults.line`).
    """

    def __init__(self, document: dict[str, Any], line: str) -> None:
        super().__init__(document)
        self._line = line

    @classmethod
    def of(cls, results: TestResults) -> ResultsObject:
        """The object of a test's results."""
        return cls(results.as_dict(), results.line())

    @classmethod
    def none(cls, reason: str) -> ResultsObject:
        """The object of a test with no results at all (no standard to follow), and why."""
        return cls({"standard": None, "not_determined": reason}, f"not determined: {reason}")

    def __str__(self) -> str:
        return self._line

    def __format__(self, spec: str) -> str:
        return format(self._line, spec)
