"""Simulator data collection, the physics-informed dynamics network and its baselines, ONNX export."""
