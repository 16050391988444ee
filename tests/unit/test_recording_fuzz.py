"""Property tests of the recording reader: any flipped bit or cut of a real recording is reported
as damage or refused in one line naming the file, never a traceback, never as a whole file.

The recording is the committed format-version-1 test (13 samples, 320 x 640), read by `info`'s
path (`recording_info`), the reader's samples and the replay's whole path
(`replay_recording`). Flips are drawn anywhere in the file, with extra weight on the header and
metadata at its start and the summary and footer at its end, where a bit carries the most
structure.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.errors import InputError
from appliance.recording.info import recording_info
from appliance.recording.reader import RecordingReader
from appliance.recording.replay import replay_recording

RECORDING = Path(__file__).parents[1] / "system" / "data" / "recording_v1"
ORIGINAL = (RECORDING / "rubber_to_8_percent.mcap").read_bytes()
SIZE = len(ORIGINAL)
STRUCTURE_BYTES = 6000


cuts = st.integers(0, SIZE - 1).map(lambda length: ("cut", length, 0))
"""The file cut to a length."""
flips = st.tuples(
    st.just("flip"),
    st.one_of(
        st.integers(0, STRUCTURE_BYTES),
        st.integers(SIZE - STRUCTURE_BYTES, SIZE - 1),
        st.integers(0, SIZE - 1),
    ),
    st.integers(0, 7),
)
"""One bit of one byte flipped."""
damages = st.one_of(cuts, flips)


def _damaged(damage: tuple[str, int, int]) -> bytes:
    kind, where, bit = damage
    if kind == "cut":
        return ORIGINAL[:where]
    data = bytearray(ORIGINAL)
    data[where] ^= 1 << bit
    return bytes(data)


@pytest.fixture(scope="module")
def scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as directory:
        yield Path(directory) / "damaged.mcap"


def _check(what: tuple[str, int, int], path: Path, read: Callable[[Path], str | None]) -> None:
    """The damage is reported in one line, or the file refused in one line naming it; any
    other exception fails the test as it is."""
    try:
        damage = read(path)
    except InputError as error:
        text = str(error)
        assert text.startswith(str(path)) and "\n" not in text, (what, text)
        return
    assert damage is not None, f"{what}: reported as whole"
    assert "\n" not in damage, (what, damage)


def _info(path: Path) -> str | None:
    return recording_info(path)["damage"]


def _samples(path: Path) -> str | None:
    reader = RecordingReader(path)
    try:
        assert sum(1 for _ in reader.samples()) <= 13
    finally:
        reader.close()
    return reader.describe_damage()


def _replay(path: Path) -> str | None:
    outcome = replay_recording(path)
    assert outcome.summary.frames_processed <= 13
    assert (outcome.summary.exit_status == "damaged") == (outcome.extra["damage"] is not None)
    return outcome.extra["damage"]


def test_the_recording_itself_is_whole(scratch):
    scratch.write_bytes(ORIGINAL)
    assert recording_info(scratch)["damage"] is None
    assert replay_recording(scratch).extra["samples_differing"] == 0


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(damage=damages)
def test_info_and_the_reader_report_any_flip_or_cut(scratch, damage):
    scratch.write_bytes(_damaged(damage))
    _check(damage, scratch, _info)
    _check(damage, scratch, _samples)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(damage=damages)
def test_replay_reports_any_flip_or_cut(scratch, damage):
    scratch.write_bytes(_damaged(damage))
    _check(damage, scratch, _replay)
