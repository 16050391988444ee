"""The Rerun viewer's configuration errors, addresses and lifecycle, without any peer process."""

from __future__ import annotations

import socket

import pytest

from appliance.config import RerunConfig
from appliance.errors import InputError
from appliance.live.viewer import RerunService, RerunViewer, has_sinks, proxy_url, viewer_blueprint
from appliance.run.loop import LoopResult
from appliance.run.state import ExitStatus


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_a_port_in_use_is_one_line_naming_the_key_and_the_address():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        viewer = RerunViewer(RerunConfig(serve=f"127.0.0.1:{port}"))
        with pytest.raises(InputError) as error:
            viewer.start()
    message = str(error.value)
    assert message.startswith(f"[rerun] serve: cannot listen on 127.0.0.1:{port} (")
    assert "in use" in message and "\n" not in message


def test_serve_needs_an_ip_address_so_nothing_is_looked_up():
    with pytest.raises(InputError, match=r"\[rerun\] serve: HOST must be an IP address"):
        RerunService("localhost:9876")
    with pytest.raises(InputError, match=r"\[rerun\] serve: must be HOST:PORT"):
        RerunService("9876")


def test_sink_configuration_errors_name_the_key(tmp_path):
    with pytest.raises(ValueError, match="no sink"):
        RerunViewer(RerunConfig())
    with pytest.raises(InputError, match=r"\[rerun\] connect: must be rerun\+http://"):
        RerunViewer(RerunConfig(connect="http://127.0.0.1:9876"))
    with pytest.raises(InputError, match=r"\[rerun\] save: .*no such directory"):
        RerunViewer(RerunConfig(save=str(tmp_path / "missing" / "test.rrd")))
    assert not has_sinks(RerunConfig())
    assert has_sinks(RerunConfig(save="x.rrd"))


def test_urls_of_a_server():
    assert proxy_url("127.0.0.1", 9876) == "rerun+http://127.0.0.1:9876/proxy"
    assert proxy_url("::1", 9876) == "rerun+http://[::1]:9876/proxy"


@pytest.mark.parametrize("history_mb", [1.0, 1.5, 65536.0])
def test_a_viewer_s_server_takes_its_history_bound_from_the_configuration(history_mb):
    viewer = RerunViewer(RerunConfig(serve=f"127.0.0.1:{_free_port()}", history_mb=history_mb))
    viewer.start()
    assert viewer.service is not None and not viewer.service.closed
    assert viewer.service.server_memory_limit == f"{history_mb:g}MB"
    viewer.close()


def test_a_service_listens_on_loopback_until_closed():
    port = _free_port()
    with RerunService(f"127.0.0.1:{port}") as service:
        assert service.url == service.local_url == f"rerun+http://127.0.0.1:{port}/proxy"
        with socket.create_connection(("127.0.0.1", port), timeout=1.0):
            pass
    assert service.closed


def test_a_viewer_without_a_test_counts_samples_as_dropped_and_ends_quietly(tmp_path):
    viewer = RerunViewer(RerunConfig(save=str(tmp_path / "{test}.rrd")))
    viewer(object())
    viewer.end(LoopResult(exit_status=ExitStatus.FAULT, reason="camera missing"))
    viewer.close()
    assert viewer.samples_dropped == 1 and viewer.samples_shown == 0
    assert viewer.recording_id is None and viewer.problem is None
    assert list(tmp_path.iterdir()) == []


def _views(part) -> list:
    contents = getattr(part, "contents", None)
    if isinstance(contents, tuple | list) and hasattr(part, "kind"):
        return [view for item in contents for view in _views(item)]
    return [part]


def test_the_blueprint_lays_out_camera_strain_force_and_status():
    views = _views(viewer_blueprint().root_container)
    assert [(view.class_identifier, str(view.origin)) for view in views] == [
        ("2D", "/camera"),
        ("TimeSeries", "/strain"),
        ("TimeSeries", "/machine"),
        ("TextDocument", "/status/state"),
        ("TextLog", "/status/log"),
        ("TextDocument", "/facts/summary"),
    ]
