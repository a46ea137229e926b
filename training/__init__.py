"""Training and evaluation of VGQ-CNN, Fast-VGQ-CNN and the GQ-CNN baseline (torch)."""
