"""Bringing a bus up: ping every device with retries, and one error that names every problem of one bus."""

from __future__ import annotations

import time


class StartupError(Exception):
    """One bus's start-up problems, one line each."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("; ".join(problems))


def ping_all(ping, ids, rounds: int, retry_s: float) -> list[int]:
    """Ping every ID, then the silent ones again, `rounds` times in all, `retry_s` apart; the IDs still silent."""
    from drivers.errors import BusTimeout

    missing = list(ids)
    for attempt in range(max(1, rounds)):
        if attempt:
            time.sleep(retry_s)
        still = []
        for device_id in missing:
            try:
                ping(device_id)
            except BusTimeout:
                still.append(device_id)
        missing = still
        if not missing:
            break
    return missing


def ids_text(ids) -> str:
    return ", ".join(str(i) for i in ids) or "none"
