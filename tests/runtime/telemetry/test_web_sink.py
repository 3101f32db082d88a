"""The `web` telemetry sink's options and link, and the one-line refusals of `bruce-run --rerun web` and
`bruce-view` (no browser needed; the browser tests are in test_web_viewer.py)."""

from __future__ import annotations

import socket
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest

from runtime.telemetry import RerunSink, parse_sink
from runtime.telemetry.sender import decimated
from runtime.telemetry.sink import recording_parts, viewer_host, web_origins, web_viewer_link
from runtime.telemetry.view_cli import main as bruce_view


@pytest.mark.parametrize("text, expected", [
    ("web", RerunSink("web")),
    ("web=8080", RerunSink("web", "8080")),
    ("web,grpc_port=9000", RerunSink("web", grpc_port=9000)),
    ("web=8080,grpc_port=9000,buffer_mb=64,host=robot.local",
     RerunSink("web", "8080", buffer_mb=64, grpc_port=9000, host="robot.local")),
    ("web,host=10.0.0.7", RerunSink("web", host="10.0.0.7")),
    ("web,host=[fe80::1]", RerunSink("web", host="[fe80::1]")),
    ("web,row_hz=250", RerunSink("web", row_hz=250.0)),
])
def test_parse_sink_reads_the_web_options(text, expected):
    assert parse_sink(text) == expected
    assert parse_sink(str(expected)) == expected


def test_web_ports_default_to_rerun_s():
    sink = parse_sink("web")
    assert (sink.web_port, sink.server_port) == (9090, 9876)
    sink = parse_sink("web=8080,grpc_port=9000")
    assert (sink.web_port, sink.server_port) == (8080, 9000)


@pytest.mark.parametrize("text, says", [
    ("web=http", "the port must be an integer in 1..65535"),
    ("web=70000", "the port must be an integer in 1..65535"),
    ("web,grpc_port=0", "grpc_port must be an integer in 1..65535, got '0'"),
    ("web,grpc_port=x", "grpc_port must be an integer in 1..65535, got 'x'"),
    ("web,host=a b", "host must be a host name or an IP address"),
    ("web,host=http://robot", "host must be a host name or an IP address"),
    ("web,host=", "host must be a host name or an IP address"),
    ("web=9876", "the web viewer (port 9876) and the gRPC server (grpc_port=9876) need different ports"),
    ("web=8000,grpc_port=8000", "need different ports"),
    ("web,max_mb=3", "unknown option 'max_mb' (web takes grpc_port=, buffer_mb=, host=, row_hz=)"),
    ("web,buffer_mb=0", "buffer_mb must be an integer number of megabytes >= 1"),
    ("serve,host=robot", "unknown option 'host' (serve takes buffer_mb=)"),
])
def test_a_bad_web_option_is_one_line_naming_it(text, says):
    with pytest.raises(ValueError) as error:
        parse_sink(text)
    message = str(error.value)
    assert says in message and repr(text) in message and "\n" not in message


def test_the_link_tells_the_viewer_where_the_stream_is():
    link = web_viewer_link("robot.local", 9090, 9876)
    parts = urlsplit(link)
    assert (parts.scheme, parts.hostname, parts.port) == ("http", "robot.local", 9090)
    assert parse_qs(parts.query) == {"url": ["rerun+http://robot.local:9876/proxy"]}
    assert "+" not in parts.query  # percent-encoded: a bare '+' in a query may be read as a space


def test_the_stream_admits_the_viewer_s_page_by_any_name():
    assert web_origins(9090) == ["http://*:9090", "https://*:9090"]


def test_the_default_host_is_reachable_from_elsewhere():
    host = viewer_host()
    assert host == socket.gethostname() or not host.startswith("127.")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize("busy_role", ["web", "grpc"])
def test_bruce_run_refuses_a_busy_port_before_anything_moves(busy_role, tmp_path, capsys):
    from runtime.cli import main as bruce_run

    web, grpc = free_port(), free_port()
    with socket.socket() as busy:
        busy.bind(("0.0.0.0", web if busy_role == "web" else grpc))
        busy.listen()
        code = bruce_run(["--backend", "mock", "--duration", "1", "--rerun", f"web={web},grpc_port={grpc}",
                          "--stats", str(tmp_path / "stats.json")])
    out, err = capsys.readouterr()
    assert "backend active" not in out  # the telemetry process starts before the backend is activated
    port, role = (web, "the web viewer") if busy_role == "web" else (grpc, "the gRPC server")
    assert code == 2
    assert f"cannot listen on port {port} for {role}" in err and "Traceback" not in err
    assert '"ticks": 0' in (tmp_path / "stats.json").read_text()


def test_recording_parts_are_found_in_order_even_after_keep_removed_the_first(tmp_path):
    run = tmp_path / "walk.rrd"
    for name in ("walk.002.rrd", "walk.010.rrd", "walk.001.rrd", "other.001.rrd", "walk.rrd.bak"):
        (tmp_path / name).write_bytes(b"x")
    assert recording_parts(run) == [tmp_path / n for n in ("walk.001.rrd", "walk.002.rrd", "walk.010.rrd")]
    run.write_bytes(b"x")
    assert recording_parts(run)[0] == run


@pytest.mark.parametrize("content, argv, says", [
    (None, ["--web"], "missing.rrd: recording file not found"),
    (b"not a recording", ["--web"], "not a readable rerun recording"),
    (b"", ["--web"], "not a readable rerun recording"),
    (None, ["--web", "--web-port", "9876"], "missing.rrd: recording file not found"),
])
def test_bruce_view_refuses_a_missing_or_corrupt_file_in_one_line(content, argv, says, tmp_path, capsys):
    path = tmp_path / ("missing.rrd" if content is None else "run.rrd")
    if content is not None:
        path.write_bytes(content)
    code = bruce_view([str(path), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and says in err[0], err
    assert err[0].startswith("bruce-view: ")


def test_bruce_view_without_a_display_points_to_web(tmp_path, monkeypatch, capsys):
    import rerun as rr

    path = tmp_path / "run.rrd"
    recording = rr.RecordingStream("bruce-view-test")
    recording.save(str(path))
    recording.log("x", rr.Scalars(1.0))
    recording.disconnect()
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert bruce_view([str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no display" in err[0] and "--web" in err[0]


def test_bruce_view_refuses_equal_ports(tmp_path, capsys):
    import rerun as rr

    path = tmp_path / "run.rrd"
    recording = rr.RecordingStream("bruce-view-test")
    recording.save(str(path))
    recording.log("x", rr.Scalars(1.0))
    recording.disconnect()
    port = free_port()
    assert bruce_view([str(path), "--web", "--web-port", str(port), "--grpc-port", str(port)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "need different ports" in err[0]


def rows_for(ticks, width: int = 8) -> np.ndarray:
    """Rows shaped as the ring's (tick, time, ..., period_us, work_us, safety_code), period 1000 and work 100."""
    rows = np.zeros((len(ticks), width))
    rows[:, 0] = ticks
    rows[:, 1] = np.asarray(ticks) / 1000
    rows[:, 2:-3] = np.asarray(ticks)[:, None] * 0.01
    rows[:, -3], rows[:, -2] = 1000.0, 100.0
    return rows


def test_decimated_rows_keep_each_interval_s_last_row_and_its_worst_timing():
    rows = rows_for(range(25))
    rows[13, -3], rows[17, -2] = 9000.0, 800.0  # one late tick, one long tick
    rows[0, -3] = np.nan                          # tick 0 has no period
    out = decimated(rows, 10)
    assert out[:, 0].tolist() == [9, 19, 24]      # the last interval is cut by the end of the send
    np.testing.assert_array_equal(out[:, 2:-3], rows[[9, 19, 24], 2:-3])  # joint values are samples, not means
    assert out[:, -3].tolist() == [1000.0, 9000.0, 1000.0] and out[:, -2].tolist() == [100.0, 800.0, 100.0]


def test_decimated_rows_follow_the_ticks_not_the_send():
    out = decimated(rows_for(range(15, 35)), 10)
    assert out[:, 0].tolist() == [19, 29, 34]
    rows = rows_for(range(5))
    assert decimated(rows, 1) is rows


@pytest.mark.parametrize("text, every", [("web", 10), ("web,row_hz=1000", 1), ("web,row_hz=250", 4),
                                         ("web,row_hz=5000", 1), ("serve", 1)])
def test_the_web_sink_sends_rows_at_row_hz(config, text, every):
    from runtime.telemetry import Telemetry

    assert config.loop_hz == 1000
    assert Telemetry(config, parse_sink(text)).row_decimation == every


@pytest.mark.parametrize("text", ["web,row_hz=0", "web,row_hz=-5", "web,row_hz=nan", "web,row_hz=fast"])
def test_a_bad_row_rate_is_refused(text):
    with pytest.raises(ValueError, match=f"{text!r}: row_hz must be a rate in Hz > 0"):
        parse_sink(text)
