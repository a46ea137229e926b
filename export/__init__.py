"""ONNX export: Fast-VGQ-CNN as an encoder graph + head graph, VGQ-CNN / GQ-CNN as one graph."""
