"""BRUCE emulated, for running the real stack with no robot: `robot` (the emulators a config describes, the MuJoCo
physics driving them; what `bruce-emulate` serves) and `process` (`bruce-emulate` as a child process, for tests,
benchmarks and the bring-up suite). The devices' byte-exact emulators are the drivers' (`drivers/emulators/`)."""
