# The scoring and planning service only: onnxruntime on CPU, no torch. Build from the repository root:
#   docker build -t vgq-service . && docker run --rm -p 8000:8000 vgq-service
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    VGQ_HOST=0.0.0.0 \
    VGQ_PORT=8000 \
    VGQ_MODEL_DIR=/app/models/fast-vgqcnn-default

WORKDIR /app
COPY pyproject.toml README.md ./
COPY vgq ./vgq
COPY service ./service
COPY planning ./planning
COPY models/fast-vgqcnn-default ./models/fast-vgqcnn-default

# the same install step as scripts/serve.sh: the package with its [service] extra
RUN pip install --no-cache-dir ".[service]" \
 && useradd --system --no-create-home --uid 10001 vgq

USER 10001
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
  CMD python -c "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2).status == 200 else 1)"
CMD ["vgq-serve"]
