"""Reading a rerun recording (.rrd) back: its entity paths, a component's rows by tick, its timelines; for the
telemetry tests (runtime/telemetry/test_telemetry.py) and bruce-run's (runtime/test_cli.py)."""


def rrd_entity_paths(path) -> set[str]:
    """Entity paths (no leading '/') of the recording in an .rrd. Reads the footer's manifest, so a file that
    was not closed properly (no footer) raises instead of answering."""
    from rerun.chunk import RrdReader

    return {p.lstrip("/") for p in RrdReader(path).store().schema().entity_paths()}


def rrd_rows(path, entity: str, component: str) -> dict[int, list]:
    """tick -> the component's values in that row, for the temporal chunks of `entity` in an .rrd."""
    from rerun.chunk import RrdReader

    rows = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/" + entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            for tick, value in zip(batch.column("tick").to_pylist(), batch.column(component).to_pylist(),
                                   strict=True):
                rows[tick] = value
    return rows


def rrd_timelines(path) -> set[str]:
    from rerun.chunk import RrdReader

    return {name for chunk in RrdReader(path).stream() for name in chunk.timeline_names}
