"""CPU scoring service: FastAPI + uvicorn + onnxruntime (no torch)."""
