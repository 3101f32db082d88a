"""Rerun telemetry for the 1 kHz loop: `sink` (where it goes), `ring` (the shared memory between the two
processes), `writer` (`Telemetry`, the control thread's side), `sender` (the telemetry process, all rerun I/O).
Design and measurements: docs/telemetry.md."""

from runtime.telemetry.sink import SINK_HELP, RerunSink, TelemetryError, grpc_url, parse_sink, part_path
from runtime.telemetry.writer import FILE_CHUNK_S, LIVE_CHUNK_S, POSE_HZ, Telemetry, make_telemetry

__all__ = ["FILE_CHUNK_S", "LIVE_CHUNK_S", "POSE_HZ", "SINK_HELP", "RerunSink", "Telemetry", "TelemetryError",
           "grpc_url", "make_telemetry", "parse_sink", "part_path"]
