"""Running a trained net outside Lightning: export to ONNX / TorchScript and streaming tracking."""
