"""Byte-exact emulators of BRUCE's devices, shipped with the package so that `bruce-run --backend hw` runs end to
end on a machine with no robot: serial devices on pseudo-terminals, CAN motors on python-can's virtual bus."""
