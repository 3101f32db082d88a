"""Which samples of a recording a model may learn from or be scored on: runs of one episode id and the transitions
inside them. The one definition the dataset, the identification of the analytic model and the evaluation use.

A transition t -> t + 1 is valid when both samples lie in one run: a recording is cut at every change of episode
id (a fall, a fresh start) and, where a part of it is taken, at the part's ends.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def episode_runs(episode: np.ndarray, start: int = 0, stop: int | None = None) -> tuple[tuple[int, int], ...]:
    """Maximal [a, b) stretches of samples [start, stop) (default: all) with one episode id, in order."""
    stop = len(episode) if stop is None else stop
    if stop <= start:
        return ()
    cuts = start + 1 + np.flatnonzero(np.diff(episode[start:stop]) != 0)
    edges = [start, *cuts.tolist(), stop]
    return tuple((int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True))


def transition_indices(episode: np.ndarray) -> np.ndarray:
    """Every t whose transition t -> t + 1 stays inside one episode."""
    return np.flatnonzero(episode[:-1] == episode[1:])


def run_indices(runs: Sequence[tuple[int, int]], before: int = 0, after: int = 1) -> np.ndarray:
    """Every t with samples t - before .. t + after inside one run, in order: the valid transitions by default;
    with `before` = a warm-up, the transitions scored after it; with `after` = a horizon, a rollout's start points."""
    parts = [np.arange(a + before, b - after) for a, b in runs]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)
