"""The 1 kHz control runtime: the loop (`loop`: the session and its tick, pacing, safety, observers), the nominal
controllers and Eq. 8/9 torque mixing (`control`), the transfer schemes (`transfer`), estimation, observation,
walking and telemetry, and the command lines `bruce-run` (`cli`) and `bruce-emulate` (`emulate_cli`)."""
