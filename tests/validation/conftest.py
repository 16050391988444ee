"""Collects the figures each validation test measured and prints them after the run.

`pytest tests/validation` ends with a table of what was measured against which bound, so the
figures quoted in the README come from a command anyone can run.
"""

from dataclasses import dataclass

import pytest

_FIGURES = pytest.StashKey[list]()


@dataclass(frozen=True)
class Figure:
    test: str
    quantity: str
    measured: float
    bound: str


class Figures:
    """Records (quantity, measured value, bound) for the running test."""

    def __init__(self, store: list, test: str) -> None:
        self._store = store
        self._test = test

    def record(self, quantity: str, measured: float, bound: str) -> None:
        self._store.append(Figure(self._test, quantity, float(measured), bound))


def pytest_configure(config: pytest.Config) -> None:
    config.stash[_FIGURES] = []


@pytest.fixture
def figures(request: pytest.FixtureRequest) -> Figures:
    return Figures(request.config.stash[_FIGURES], request.node.nodeid.split("::")[-1])


def pytest_terminal_summary(terminalreporter, config: pytest.Config) -> None:
    recorded = config.stash.get(_FIGURES, [])
    if not recorded:
        return
    terminalreporter.section("validation figures (measured / bound)")
    for figure in recorded:
        terminalreporter.write_line(
            f"{figure.test}: {figure.quantity} = {figure.measured:.6g} (bound {figure.bound})"
        )
