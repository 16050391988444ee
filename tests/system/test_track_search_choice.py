"""`extensometer track`'s search choice on a large one-step stretch under motion blur: a real
process on rendered 8-bit image files with their exact truth."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.dic.blur import motion_blur
from appliance.dic.synthetic import (
    AffineMapping,
    add_gaussian_noise,
    gaussian_speckle,
    quantize,
    render,
)

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
WIDTH, HEIGHT = 640, 360
STRETCH = 0.4
BLUR_PX = 10.0


@pytest.fixture(scope="module")
def stretched(tmp_path_factory):
    root = tmp_path_factory.mktemp("stretch")
    pattern = gaussian_speckle(WIDTH, HEIGHT, count=1100, radius=4.0, seed=9)
    mapping = AffineMapping(
        u=20.0, v=4.0, ux=STRETCH, vy=(1 + STRETCH) ** -0.5 - 1, xc=WIDTH / 2, yc=HEIGHT / 2
    )
    reference = render(pattern, HEIGHT, WIDTH)
    target = motion_blur(render(pattern, HEIGHT, WIDTH, mapping), BLUR_PX, 0.0)
    cv2.imwrite(str(root / "ref.png"), quantize(add_gaussian_noise(reference, 2.0, seed=1), 8))
    cv2.imwrite(str(root / "tgt.png"), quantize(add_gaussian_noise(target, 2.0, seed=2), 8))
    ys, xs = np.mgrid[140:221:20, 200:441:20]
    points = np.c_[xs.ravel(), ys.ravel()].astype(float)
    (root / "points.csv").write_text(
        "x,y\n" + "".join(f"{x:g},{y:g}\n" for x, y in points), encoding="utf-8"
    )
    x, y = mapping.forward(points[:, 0], points[:, 1])
    return root, np.c_[x - points[:, 0], y - points[:, 1]]


def _track(root: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "track", root / "ref.png", root / "tgt.png", "--points", root / "points.csv"]
        + list(options),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def run_track(root: Path, *options: str) -> dict:
    done = _track(root, "--json", "--threads", "1", *options)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def within_half_pixel(document: dict, truth: np.ndarray) -> float:
    points = document["images"][0]["points"]
    hits = [
        p["u"] is not None and np.hypot(p["u"] - u, p["v"] - v) <= 0.5
        for p, (u, v) in zip(points, truth, strict=True)
    ]
    return float(np.mean(hits))


def test_the_default_search_recovers_a_40_percent_stretch_under_known_blur(stretched):
    root, truth = stretched
    plain = run_track(root, "--search", "zncc", "--blur-px", str(BLUR_PX))
    default = run_track(root, "--blur-px", str(BLUR_PX))
    assert within_half_pixel(plain, truth) < 0.85
    assert within_half_pixel(default, truth) >= 0.95
    search = default["search"]
    assert search["requested"] == "auto"
    assert search["method"] == "zncc"
    assert search["reference_blur_px"] == BLUR_PX
    assert search["recover"] is True
    assert search["reason"]
    image = default["images"][0]["search"]
    assert image["recovered"] > 0
    assert image["icgn_reference_blur_px"] == pytest.approx(BLUR_PX / (1 + STRETCH), abs=0.25)


def test_a_given_stretch_range_searches_every_point_over_its_prewarps(stretched):
    root, truth = stretched
    told = run_track(root, "--blur-px", str(BLUR_PX), "--stretch", "0.3:0.5")
    assert told["search"]["stretch"] == [0.3, 0.5]
    assert told["search"]["prewarps"] == 5
    assert within_half_pixel(told, truth) >= 0.95


def test_lpq_reports_the_window_of_the_blur_rule(stretched):
    root, _ = stretched
    document = run_track(root, "--search", "lpq", "--blur-px", "6")
    assert document["search"]["method"] == "lpq"
    assert document["search"]["lpq_window"] == 19
    given = run_track(root, "--search", "lpq", "--lpq-window", "11")
    assert given["search"]["lpq_window"] == 11


def test_a_malformed_stretch_range_is_one_line_naming_the_option(stretched):
    root, _ = stretched
    done = _track(root, "--stretch", "0.5")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert "--stretch" in lines[-1] and "LOW:HIGH" in lines[-1]
