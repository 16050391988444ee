import pytest

from appliance.config import Config, load_config, parse_config
from appliance.errors import InputError


def test_empty_file_gives_the_defaults_and_values_are_typed():
    assert parse_config("") == Config()
    config = parse_config(
        "[camera]\nexposure_us = 250\npixel_format = 'Mono12'\n"
        "[tracking]\nsubset_px = 31\nsearch = 'lpq'\n[run]\nuntil_break = false\n"
    )
    assert config.camera.exposure_us == 250.0 and isinstance(config.camera.exposure_us, float)
    assert config.tracking.subset_px == 31 and config.tracking.search == "lpq"
    assert config.run.until_break is False


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[camera]\nexposure_ms = 3\n", "run.toml: [camera]: unknown key 'exposure_ms'"),
        ("[cameras]\n", "run.toml: unknown key 'cameras'"),
        ("[camera]\nexposure_us = -5\n", "run.toml: [camera] exposure_us: must be >= 1, got -5"),
        ("[camera]\nexposure_us = 'fast'\n", "[camera] exposure_us: must be a number"),
        ("[tracking]\nsubset_px = 40\n", "[tracking] subset_px: must be odd, got 40"),
        ("[tracking]\nsubset_px = 41.0\n", "[tracking] subset_px: must be an integer"),
        ("[tracking]\nsearch = 'sift'\n", "[tracking] search: must be one of none, zncc, lpq"),
        ("[run]\nuntil_break = 1\n", "[run] until_break: must be true or false"),
        ("[run]\nspeed_mm_min = nan\n", "[run] speed_mm_min: must be finite"),
        ("camera = 3\n", "run.toml: [camera]: must be a table"),
        ("[tracking]\nmin_subset_px = 51\n", "[tracking] min_subset_px: must be <= subset_px"),
        ("[camera]\nmin_exposure_us = 3e4\n", "[camera] min_exposure_us: must be <= max_exp"),
        ("[camera\n", "run.toml: invalid TOML"),
    ],
)
def test_every_bad_value_is_named_in_one_line(text, message):
    with pytest.raises(InputError) as info:
        parse_config(text, "run.toml")
    assert message in str(info.value) and "\n" not in str(info.value)


def test_files(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("[gauge]\nlength_mm = 50\n")
    assert load_config(path).gauge.length_mm == 50.0
    with pytest.raises(InputError, match="no such configuration file"):
        load_config(tmp_path / "absent.toml")
