"""The `extensometer track` command as a user runs it: a real process, real image files."""

import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.unit.cosine_texture import CosineTexture

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
SIZE = 240
SHIFTS = [(2.3, -1.6), (4.7, -3.1)]


def track(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "track", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("track")
    texture = CosineTexture(seed=21)
    reference = root / "ref.png"
    cv2.imwrite(
        str(reference), np.clip(np.round(texture.image(SIZE, SIZE)), 0, 255).astype(np.uint8)
    )
    targets = []
    for k, (du, dv) in enumerate(SHIFTS):
        image = texture.image(SIZE, SIZE, inverse=lambda x, y, du=du, dv=dv: (x - du, y - dv))
        path = root / f"img{k}.tif"
        cv2.imwrite(str(path), (np.clip(image, 0, 255) * 257).astype(np.uint16))
        targets.append(path)
    points = root / "points.csv"
    points.write_text("x,y\n80,80\n160,80\n120,160\n")
    return root, reference, targets, points


@pytest.mark.parametrize("method", ["lpq", "zncc", "none"])
def test_json_output_has_the_documented_shape_and_the_truth(scene, method):
    _, reference, targets, points = scene
    radius = "0" if method == "none" else "10"
    done = track(
        reference,
        *targets,
        "--points",
        points,
        "--subset",
        "31",
        "--search",
        method,
        "--search-radius",
        radius,
        "--json",
    )
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert [Path(i["path"]).name for i in document["images"]] == ["img0.tif", "img1.tif"]
    for image, (du, dv) in zip(document["images"], SHIFTS, strict=True):
        assert len(image["points"]) == 3
        for point in image["points"]:
            assert set(point) == {
                "x",
                "y",
                "u",
                "v",
                "ux",
                "uy",
                "vx",
                "vy",
                "zncc",
                "iterations",
                "status",
            }
            assert point["status"] == "converged"
            assert abs(point["u"] - du) < 0.02 and abs(point["v"] - dv) < 0.02
            assert point["zncc"] > 0.999


def test_out_file_and_table(scene, tmp_path):
    _, reference, targets, points = scene
    out = tmp_path / "result.json"
    done = track(reference, targets[0], "--points", points, "--subset", "31", "--out", out)
    assert done.returncode == 0 and done.stdout == ""
    assert len(json.loads(out.read_text())["images"]) == 1
    table = track(reference, targets[0], "--points", points, "--subset", "31")
    assert table.returncode == 0 and "converged" in table.stdout


def error_of(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "Traceback" not in done.stderr
    return lines[0]


def test_bad_inputs_end_in_one_line_naming_the_culprit(scene, tmp_path):
    root, reference, targets, points = scene
    assert "absent.png" in error_of(track(reference, tmp_path / "absent.png", "--points", points))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((50, 60), np.uint8))
    assert "small.png: size 60x50 differs" in error_of(track(reference, small, "--points", points))
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n10,10\n3,x\n")
    assert "bad.csv:3:" in error_of(track(reference, targets[0], "--points", bad))
    edge = tmp_path / "edge.csv"
    edge.write_text("x,y\n120,120\n10,120\n")
    message = error_of(track(reference, targets[0], "--points", edge, "--subset", "41"))
    assert "edge.csv:3: subset 41x41 at (10, 120) reaches outside" in message
    assert "--search" in error_of(track(reference, targets[0], "--points", points, "--search", "x"))
    assert "--subset" in error_of(
        track(reference, targets[0], "--points", points, "--subset", "40")
    )


def test_a_point_not_found_has_no_displacement_only_a_status_saying_why(scene, tmp_path):
    _, reference, targets, _ = scene
    flat = tmp_path / "flat.png"
    image = cv2.imread(str(reference), cv2.IMREAD_UNCHANGED)
    image[50:110, 50:110] = 128
    cv2.imwrite(str(flat), image)
    points = tmp_path / "points.csv"
    points.write_text("x,y\n80,80\n160,80\n")
    done = track(flat, targets[0], "--points", points, "--subset", "31", "--json")
    assert done.returncode == 0, done.stderr
    lost, found = json.loads(done.stdout)["images"][0]["points"]
    assert lost["status"] == "flat_subset"
    assert all(lost[key] is None for key in ("u", "v", "ux", "uy", "vx", "vy"))
    assert found["status"] == "converged" and abs(found["u"] - SHIFTS[0][0]) < 0.05
    table = track(flat, targets[0], "--points", points, "--subset", "31")
    assert "flat_subset" in table.stdout and "-50" not in table.stdout


def _png_claiming(width: int, height: int) -> bytes:
    """A PNG whose header claims `width` x `height` 8-bit grey pixels, with almost no data."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    pixels = zlib.compress(b"\x00" * 100)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize(
    ("option", "value"),
    [("--prefilter-sigma", "1e308"), ("--blur-px", "1e9"), ("--search-radius", "100000")],
)
def test_values_beyond_their_physical_range_are_refused_naming_the_option(scene, option, value):
    _, reference, targets, points = scene
    assert option in error_of(track(reference, targets[0], "--points", points, option, value))


def test_an_image_whose_header_claims_billions_of_pixels_is_refused_in_one_line(scene, tmp_path):
    _, reference, targets, points = scene
    huge = tmp_path / "huge.png"
    huge.write_bytes(_png_claiming(60000, 60000))
    assert "huge.png: not a readable image" in error_of(track(huge, targets[0], "--points", points))
    assert "huge.png: not a readable image" in error_of(track(reference, huge, "--points", points))


def test_measured_images_survive_a_later_bad_image(scene, tmp_path):
    _, reference, targets, points = scene
    out = tmp_path / "partial.json"
    done = track(
        reference,
        targets[0],
        tmp_path / "gone.png",
        "--points",
        points,
        "--subset",
        "31",
        "--out",
        out,
    )
    assert "gone.png" in error_of(done)
    images = json.loads(out.read_text())["images"]
    assert len(images) == 1 and images[0]["points"][0]["status"] == "converged"
