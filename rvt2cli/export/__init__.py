"""Deployable policies: ONNX or TorchScript, with a manifest and the instruction embeddings, parity-checked."""
