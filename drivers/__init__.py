"""Wire protocols of BRUCE's devices: BEAR (RS-485), Dynamixel, the sense board and CAN motors.

Vendor SDKs are imported lazily inside each driver so that the rest of the stack imports without them.
"""
