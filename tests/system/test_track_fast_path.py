"""`extensometer track`'s batched path measures what the per-point `Correlator` measures.

track searches all points in batches, refines them on `--threads` workers and reads the next
image ahead; `appliance.dic.correlation.Correlator` is the plain path (one `matchTemplate` per
point). The IC-GN arithmetic is the same, so on images where the searches find the same
integer peaks every number of the JSON is the plain path's, bit for bit, on any thread count.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.dic.correlation import Correlator, PointStatus
from appliance.dic.synthetic import AffineMapping, add_gaussian_noise, dense_speckle, quantize
from appliance.dic.synthetic import render as render_speckle

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
SIZE = 300
SUBSET = 21
STEPS = [(2.3, -1.6), (4.7, -3.1), (6.2, -5.4)]
FIELDS = ("u", "v", "ux", "uy", "vx", "vy", "zncc", "iterations", "status")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("track_fast")
    pattern = dense_speckle(SIZE, SIZE, seed=11)
    paths = []
    for k, (du, dv) in enumerate([(0.0, 0.0), *STEPS]):
        image = render_speckle(pattern, SIZE, SIZE, AffineMapping.translation(du, dv))
        path = root / f"image{k}.png"
        cv2.imwrite(str(path), quantize(add_gaussian_noise(image, 2.0, seed=k)))
        paths.append(path)
    g = np.linspace(30, SIZE - 31, 9)
    xy = np.array([(x, y) for y in g for x in g])
    points = root / "points.csv"
    points.write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in xy), encoding="utf-8")
    return paths[0], paths[1:], points, xy


def track_json(reference, targets, points, *options: str) -> dict:
    done = subprocess.run(
        [EXTENSOMETER, "track", str(reference), *map(str, targets), "--points", str(points)]
        + ["--subset", str(SUBSET), "--json", *options],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def plain_path(reference, targets, xy, search: str, radius: int, blur_px: float) -> list[dict]:
    correlator = Correlator(
        subset=SUBSET,
        search=search,
        search_radius=radius,
        reference_blur=(blur_px, 30.0) if blur_px else None,
    )
    correlator.prepare(cv2.imread(str(reference), cv2.IMREAD_UNCHANGED).astype(float), xy)
    guess = np.zeros((len(xy), 2))
    images = []
    for path in targets:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(float)
        result = correlator.measure(image, guess).refinement
        converged = result.status == PointStatus.CONVERGED
        guess[converged] = np.c_[result.u, result.v][converged]
        images.append({name: getattr(result, name) for name in FIELDS})
    return images


@pytest.mark.parametrize(
    "search, radius, blur_px",
    [("zncc", 8, 0.0), ("zncc", 3, 2.0), ("lpq", 6, 0.0), ("none", 0, 0.0)],
)
def test_every_number_is_the_plain_paths_on_one_thread_and_two(scene, search, radius, blur_px):
    reference, targets, points, xy = scene
    options = ["--search", search, "--search-radius", str(radius)]
    if blur_px:
        options += ["--blur-px", str(blur_px), "--blur-angle-deg", "30"]
    one = track_json(reference, targets, points, *options, "--threads", "1")
    two = track_json(reference, targets, points, *options, "--threads", "2")
    assert one["images"] == two["images"]
    assert (one["throughput"]["threads"], two["throughput"]["threads"]) == (1, 2)
    expected = plain_path(reference, targets, xy, search, radius, blur_px)
    for image, plain in zip(one["images"], expected, strict=True):
        status = [p["status"] for p in image["points"]]
        assert status == [PointStatus(int(s)).name.lower() for s in plain["status"]]
        assert status.count("converged") >= len(xy) - 2
        for name in ("zncc", "iterations"):
            assert [p[name] for p in image["points"]] == plain[name].tolist()
        found = plain["status"] == PointStatus.CONVERGED
        for name in ("u", "v", "ux", "uy", "vx", "vy"):
            measured = [p[name] for p, ok in zip(image["points"], found, strict=True) if ok]
            assert measured == plain[name][found].tolist()


def test_json_says_the_throughput(scene):
    reference, targets, points, xy = scene
    document = track_json(reference, targets, points, "--search-radius", "5")
    throughput = document["throughput"]
    assert set(throughput) == {"points_per_s", "images_per_s", "seconds", "threads"}
    assert throughput["images_per_s"] == pytest.approx(len(targets) / throughput["seconds"])
    assert throughput["points_per_s"] == pytest.approx(
        len(xy) * len(targets) / throughput["seconds"]
    )
    assert throughput["threads"] >= 1


def test_a_thread_count_beyond_the_host_is_refused_naming_the_option(scene):
    reference, targets, points, _ = scene
    done = subprocess.run(
        [EXTENSOMETER, "track", str(reference), str(targets[0]), "--points", str(points)]
        + ["--threads", "100000"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 2
    assert "--threads" in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
