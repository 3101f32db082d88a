"""The nominal controllers and what they compute with: the controllers by name (`controllers`), the walking policy
(`policy`, its interface `policy_spec`, its ONNX session and the PINN's in `inference`), the standing controller
(`standing`), the velocity commands (`commands`) and the heading they ask for (`heading`), and the paper's torque
mixing laws (`mixing`: Eq. 8 and Eq. 9).

Nothing is imported here, so that a module of the package loads only what it needs."""
