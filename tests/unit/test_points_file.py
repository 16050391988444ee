import numpy as np
import pytest

from appliance.cli.points_file import read_points
from appliance.errors import InputError


def write(tmp_path, text):
    path = tmp_path / "points.csv"
    path.write_text(text)
    return path


def test_reads_xy_and_guess_in_any_column_order(tmp_path):
    points = read_points(write(tmp_path, "v0,x,y,u0\n# comment\n1.5,10,20,-2\n\n0,30.5,40,0.25\n"))
    np.testing.assert_array_equal(points.xy, [[10, 20], [30.5, 40]])
    np.testing.assert_array_equal(points.guess, [[-2, 1.5], [0.25, 0]])
    np.testing.assert_array_equal(points.lines, [3, 5])


def test_guess_is_optional(tmp_path):
    points = read_points(write(tmp_path, "x,y\n1,2\n"))
    assert points.guess is None and points.xy.shape == (1, 2)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty points file"),
        ("a,b\n1,2\n", ":1: header must be x,y"),
        ("x,y\n", "no points after the header"),
        ("x,y\n1,2\n3\n", ":3: expected 2 values, got 1"),
        ("x,y\n1,2\n3,four\n", ":3: y='four' is not a number"),
        ("x,y,u0,v0\n1,2,nan,0\n", ":2: u0=nan is not finite"),
    ],
)
def test_bad_files_name_file_and_line(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(InputError, match=message) as info:
        read_points(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such points file"):
        read_points(tmp_path / "absent.csv")
