"""The 1 kHz control runtime: nominal controller, Eq. 8/9 torque mixing, pacing, and the `bruce-run` CLI."""
