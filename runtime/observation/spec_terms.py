"""A spec's observation from registered terms (`SpecTerms`): each term's function, then, the same for every term
and any batch, the spec's joint order, offset, clip, scale (Isaac Lab's order: clip, then scale) and history, and
last the spec's obs_clip."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from runtime.control.policy_spec import ObservationTerm, PolicySpec
from runtime.observation.inputs import ObservationInputs
from runtime.observation.registry import OBSERVATION_TERMS


class _TermSteps:
    """One of the spec's terms: its function and which steps change anything (an identity costs nothing and keeps
    the term's values exact)."""

    def __init__(self, term: ObservationTerm, spec: PolicySpec):
        self.term = term
        definition = OBSERVATION_TERMS[term.term]
        self.function = definition.function
        order = spec.order
        self.order = order if definition.per_joint and not np.array_equal(order, np.arange(len(order))) else None
        self.offset = bool(np.any(term.offset))
        self.scale = bool(np.any(term.scale != 1.0))

    def frame(self, inputs: ObservationInputs, batch: int) -> np.ndarray:
        """(N, width): this tick's frame of the term (N = `batch`)."""
        t = self.term
        x = np.asarray(self.function(inputs))
        if x.shape != (batch, t.width):
            raise ValueError(f"observation term {t.term!r}: its function returned shape {x.shape}, expected "
                             f"({batch}, {t.width})")
        if self.order is not None:
            x = x[:, self.order]
        if self.offset:
            x = np.subtract(x, t.offset)
        if t.clip is not None:
            x = np.minimum(np.maximum(x, -t.clip), t.clip)  # np.clip's values, without its Python layer
        if self.scale:
            x = np.multiply(x, t.scale)
        return x


class SpecTerms:
    """The observation `spec` asks for, of a batch of `batch` robots, from their `ObservationInputs`, once per
    policy tick, in order. A term with history keeps each robot's last frames, all equal to the robot's first one
    after its reset (as Isaac Lab's history buffers start)."""

    def __init__(self, spec: PolicySpec, batch: int):
        self.spec = spec
        self.size = spec.obs_size
        self.steps = [_TermSteps(term, spec) for term in spec.terms]
        ends = np.cumsum([0] + [t.size for t in spec.terms])
        self.slices = [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:], strict=True)]  # each term's values
        # (N, history, width) per term with history, newest frame in [:, 0]
        self.frames = [np.zeros((batch, t.history, t.width)) if t.history > 1 else None for t in spec.terms]
        self.started = np.zeros(batch, dtype=bool)

    def reset(self, envs=...) -> None:
        """The robots `envs` (a mask or indices into the batch) start a run: their history restarts."""
        self.started[envs] = False

    def __call__(self, inputs: ObservationInputs) -> np.ndarray:
        batch = inputs.batch
        obs = np.empty((batch, self.size))
        restart = None  # the robots whose history restarts this tick (looked up at the first term with history)
        for steps, frames, where in zip(self.steps, self.frames, self.slices, strict=True):
            x = steps.frame(inputs, batch)
            if frames is not None:
                frames[:, 1:] = frames[:, :-1]
                frames[:, 0] = x
                if restart is None:
                    restart = np.flatnonzero(~self.started)
                if len(restart):
                    frames[restart] = x[restart, None, :]
                x = (frames if steps.term.newest_first else frames[:, ::-1]).reshape(batch, steps.term.size)
            obs[:, where] = x
        self.started[:] = True
        clip = self.spec.obs_clip
        if clip is not None:  # np.clip's values, without its Python layer
            np.maximum(obs, -clip, out=obs)
            np.minimum(obs, clip, out=obs)
        return obs

    def get_state(self) -> dict[str, Any]:
        """The history, for a checkpoint."""
        return {"frames": [None if f is None else f.copy() for f in self.frames], "started": self.started.copy()}

    def set_state(self, saved: Mapping[str, Any]) -> None:
        self.frames = [None if f is None else np.array(f, dtype=float) for f in saved["frames"]]
        self.started = np.array(saved["started"], dtype=bool)
