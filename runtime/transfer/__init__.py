"""The transfer stage: what runs after Eq. 8 and before safety on every tick (`schemes`: direct, the paper's Eq. 9,
shadow, observer, twin, shadow_twin), the models it predicts with (`reference_models`: the ONNX PINN or the nominal
MuJoCo model; `nominal_twin` and `twin_runner`: the live twin and the thread it runs on), the gains it derives
(`gains`), and what watches it (`gap_monitor`: the live one-step residual; `twin_metric`: the rehearsal's twin
offset). docs/transfer.md."""
