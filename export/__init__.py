"""ONNX export of the normal-flow head (:func:`export_onnx`) and its torch/onnxruntime parity."""

from evseg.export.onnx import OPSET, export_onnx, model_metadata, parity

__all__ = ["OPSET", "export_onnx", "model_metadata", "parity"]
