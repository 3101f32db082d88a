"""The dynamics models (the PINN and its baselines), their checkpoints, training (`bruce-train`) and ONNX export
(`bruce-export`)."""
