"""The leg bus kinds, one module each: what a robot config needs to use it, its `LegBus` for the hw backend, its
emulators and their torque law for the emulated plant, and its bruce-hw-check diagnosis. They are registered in
`bruce_hw.leg_kinds`; docs/extending.md ("Adding a leg actuator") walks through adding one."""
