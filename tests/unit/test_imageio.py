import cv2
import numpy as np
import pytest
from PIL import Image

from appliance.cli.image_files import read_grey
from appliance.errors import InputError

GREY = (np.arange(48 * 64) * 7 % 256).astype(np.uint8).reshape(48, 64)


@pytest.mark.parametrize("suffix", [".png", ".bmp", ".tif"])
def test_reads_8_bit_grey(tmp_path, suffix):
    path = tmp_path / f"image{suffix}"
    assert cv2.imwrite(str(path), GREY)
    image = read_grey(path)
    assert image.dtype == np.uint8 and np.array_equal(image, GREY)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_reads_16_bit_grey(tmp_path, suffix):
    data = GREY.astype(np.uint16) * 257
    path = tmp_path / f"image{suffix}"
    assert cv2.imwrite(str(path), data)
    image = read_grey(path)
    assert image.dtype == np.uint16 and np.array_equal(image, data)


def test_reads_palette_tiff_through_its_palette(tmp_path):
    path = tmp_path / "palette.tif"
    picture = Image.fromarray(GREY, "L").convert("P")
    picture.putpalette([level for i in range(256) for level in (255 - i,) * 3])
    picture.save(path)
    assert Image.open(path).mode == "P"
    assert np.array_equal(read_grey(path), 255 - GREY)


def test_colour_image_becomes_luminance(tmp_path):
    path = tmp_path / "colour.png"
    colour = np.dstack([GREY, np.zeros_like(GREY), 255 - GREY])
    cv2.imwrite(str(path), colour)
    image = read_grey(path)
    assert image.shape == GREY.shape
    assert np.array_equal(image, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))


def test_missing_and_unreadable_files_are_named(tmp_path):
    with pytest.raises(InputError, match="absent.png: no such image file"):
        read_grey(tmp_path / "absent.png")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(InputError, match="junk.png: not a readable image"):
        read_grey(junk)
    empty = tmp_path / "empty.tif"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty.tif: not a readable image"):
        read_grey(empty)
