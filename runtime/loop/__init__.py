"""The 1 kHz loop and what runs around it: one session (`run`: start-up, the read -> update -> write tick,
shutdown), its pacing (`pacing`) and statistics (`loopstats`), the real-time scheduling it asks for (`realtime`),
the safety stage before every write (`safety`), the tick's observers (`observers`: evaluation, with the fall rule of
`falls`; `recorder`: `bruce-run --record`), and how a run ends (`exit`: exit codes and signals).

Nothing is imported here: `runtime.loop.exit` must stay light enough for `bruce-run` to take the signals over
before numpy, MuJoCo or onnxruntime load."""
