import json
import re

import pytest

from appliance.config import (
    Config,
    Override,
    config_from_table,
    config_to_table,
    load_config,
    merge_tables,
    parse_config,
    with_overrides,
)
from appliance.errors import InputError
from appliance.measure.tracking import TrackerSettings


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
        ("[tracking]\nsearch_radius_px = 0\n", "[tracking] search_radius_px: must be >= 1"),
        ("[camera]\nmin_exposure_us = 3e4\n", "[camera] min_exposure_us: must be <= max_exp"),
        ("[camera\n", "run.toml: invalid TOML"),
        ("[camera]\nregion_width_px = 512\n", "[camera] region_x_px: required with the other"),
        ("[machine]\nregisters = 3\n", "run.toml: [machine] registers: must be a table"),
        (
            "[camera]\nurl = 'sim://bench?bogus=1'\n",
            "run.toml: [camera] url: 'sim://bench?bogus=1': a simulated device takes no options",
        ),
        ("[machine]\nurl = 'sim://machine#x'\n", "[machine] url: 'sim://machine#x': a simul"),
        (
            "[machine.registers]\npreset = 'generic'\nforce_n = { data_type = 'float' }\n",
            "run.toml: [machine.registers.force_n] data_type: must be one of",
        ),
    ],
)
def test_every_bad_value_is_named_in_one_line(text, message):
    with pytest.raises(InputError) as info:
        parse_config(text, "run.toml")
    assert message in str(info.value) and "\n" not in str(info.value)


def test_hardware_tables_are_typed_and_the_register_map_defaults_to_the_generic_preset():
    from appliance.config import register_map_of
    from hal.machine.register_map import GENERIC_CONTROLLER

    config = parse_config(
        "[camera]\nurl = 'aravis://127.0.0.1'\npixel_format = 'Mono16'\nregion_x_px = 0\n"
        "region_y_px = 8\nregion_width_px = 512\nregion_height_px = 256\n"
        "[machine]\nurl = 'modbus-tcp://127.0.0.1:5020'\npoll_rate_hz = 200\n"
        "[machine.registers]\npreset = 'generic'\n"
        "force_n = { address = 10, table = 'holding', data_type = 'int32', scale = 0.1 }\n"
        "[gauge]\ncentre_x_px = 100.5\naxis_deg = 0\n"
    )
    assert config.camera.region_height_px == 256 and config.machine.poll_rate_hz == 200.0
    assert config.gauge.axis_deg == 0.0 and config.gauge.centre_y_px is None
    custom = register_map_of(config)
    assert custom.entries()["force_n"].address == 10 and custom.entries()["force_n"].scale == 0.1
    assert custom.entries()["crosshead_mm"] == GENERIC_CONTROLLER.entries()["crosshead_mm"]
    assert register_map_of(Config()) is GENERIC_CONTROLLER
    assert config_from_table(config_to_table(config)) == config


def test_files(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("[gauge]\nlength_mm = 50\n")
    assert load_config(path).gauge.length_mm == 50.0
    with pytest.raises(InputError, match="no such configuration file"):
        load_config(tmp_path / "absent.toml")


def test_output_tables_and_addresses():
    config = parse_config(
        "[modbus]\ntcp = '127.0.0.1:5020'\nallow_write_from = ['127.0.0.1']\n"
        "[rerun]\nserve = '[::1]:9876'\n[record]\nfull_frame_rate_hz = 0\n"
    )
    assert config.modbus.allow_write_from == ("127.0.0.1",)
    assert config.record.full_frame_rate_hz == 0.0
    for text, message in [
        ("[modbus]\ntcp = '127.0.0.1'\n", "[modbus] tcp: must be HOST:PORT"),
        ("[modbus]\ntcp = 'localhost:70000'\n", "[modbus] tcp: must be HOST:PORT"),
        ("[modbus]\nallow_write_from = '10.0.0.1'\n", "[modbus] allow_write_from: must be a list"),
        ("[modbus]\nword_order = 'middle'\n", "[modbus] word_order: must be one of big, little"),
        ("[service]\nstart = 'now'\n", "[service] start: must be one of command, auto"),
    ]:
        with pytest.raises(InputError, match=re.escape(message)):
            parse_config(text, "x.toml")


def test_a_configuration_survives_its_table_form():
    config = parse_config(
        "[camera]\nexposure_us = 250\n[modbus]\nallow_write_from = ['::1']\n"
        "[gauge]\nlength_mm = 50\n"
    )
    table = config_to_table(config)
    assert "frame_rate_hz" not in table["camera"]
    assert config_from_table(json.loads(json.dumps(table))) == config
    merged = merge_tables(table, {"tracking": {"subset_px": 31}})
    assert config_from_table(merged).tracking.subset_px == 31
    assert config_from_table(merged).camera.exposure_us == 250.0


def test_the_tracking_table_is_the_trackers_settings_with_one_default_per_key():
    assert Config().tracking == TrackerSettings()
    table = config_to_table(Config())["tracking"]
    assert "axis" not in table and "margin_px" not in table and "blur_tolerance_px" not in table
    with pytest.raises(InputError, match=re.escape("x.toml: [tracking]: unknown key 'margin_px'")):
        parse_config("[tracking]\nmargin_px = 2\n", "x.toml")


def test_overrides_are_checked_as_a_file_is_and_name_their_option():
    config = with_overrides(
        parse_config("[run]\nspeed_mm_min = 50\n"),
        [
            Override("--speed-mm-min", "run", "speed_mm_min", 20),
            Override("--modbus-tcp", "modbus", "tcp", "127.0.0.1:5020"),
        ],
    )
    assert config.run.speed_mm_min == 20.0 and isinstance(config.run.speed_mm_min, float)
    assert config.modbus.tcp == "127.0.0.1:5020"
    for override, message in (
        (Override("--speed-mm-min", "run", "speed_mm_min", 2e4), "--speed-mm-min: must be <= "),
        (Override("--modbus-tcp", "modbus", "tcp", "127.0.0.1"), "--modbus-tcp: must be HOST:PORT"),
        (Override("--material", "sim", "material", "wood"), "--material: must be one of"),
    ):
        with pytest.raises(InputError) as caught:
            with_overrides(Config(), [override])
        assert str(caught.value).startswith(message), str(caught.value)
    with pytest.raises(
        InputError, match=re.escape("[tracking] min_subset_px: must be <= subset_px")
    ):
        with_overrides(Config(), [Override("--subset", "tracking", "subset_px", 9)])
