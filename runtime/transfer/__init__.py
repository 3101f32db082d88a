"""The transfer stage: what runs after Eq. 8 and before safety on every tick. One scheme per module (`direct`, `eq9`
(the paper's Eq. 9, also `pinn`), `shadow`, `observer`, `twin` (twin, shadow_twin)), each registering itself by
name with its settings (`registry`, `settings`; `stage`: the `transfer` section of the robot config; `schemes`:
building one by name); the models they predict with (`reference_models`: the ONNX PINN or the nominal MuJoCo model;
`nominal_twin` and `twin_runner`: the live twin and the thread it runs on), the gains they derive (`gains`), and
what watches them (`gap_monitor`: the live one-step residual; `twin_metric`: the rehearsal's twin offset).
docs/transfer.md; adding a scheme: docs/extending.md ("Adding a transfer scheme")."""

# The shipped schemes register themselves on import; importing anything of the package makes the registry whole.
from runtime.transfer import direct, eq9, shadow, observer, twin  # noqa: F401, I001  (registration, in this order)
