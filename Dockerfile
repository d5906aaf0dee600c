# syntax=docker/dockerfile:1
#
# The DPC-MN pose service: the runtime dependencies only (numpy, scipy, onnxruntime, FastAPI;
# no torch), the shipped model under /app/models, a non-root user, the gallery on a volume.
#
#   docker build -t dpc-mn-service .
#   docker run -d -p 8000:8000 -v dpc-data:/data --name dpc dpc-mn-service
#   curl -s localhost:8000/health
#   curl -s -X POST localhost:8000/align -H 'Content-Type: application/json' \
#       --data @models/sample_cloud.json
#   open http://localhost:8000/ui/ : the web console, shipped in the package (service/console)
#
# Build arguments:
#   ONNXRUNTIME   "onnxruntime" (the default: CPU) or "onnxruntime-gpu": swaps in the CUDA
#                 build of the same minor version, with NVIDIA's CUDA and cuDNN libraries from
#                 their pip wheels (registered with ldconfig). Run it with `docker run --gpus all`
#                 (NVIDIA Container Toolkit on the host) and check that /health lists
#                 CUDAExecutionProvider; without a GPU the service falls back to the CPU.
#                   docker build --build-arg ONNXRUNTIME=onnxruntime-gpu -t dpc-mn-service:gpu .
#   PYTHON_IMAGE  the base image, pinned to a patch release (pin its digest for a release build).
#   EXTRAS        "fast" (the default): the engine's innermost loops compiled by numba, POST
#                 /detect takes half the time; "" leaves numba out (an image 0.2 GB smaller).
#
# Settings are environment variables DPC_<GROUP>__<FIELD> (service/settings.py), e.g.
#   docker run -e DPC_ENGINE__TOP_K=5 -e DPC_AUTH__KEYS='{"<key>": "admin"}' ...
# The gallery (SQLite) lives in the /data volume; it is seeded from models/gallery.npz on the
# first start and survives the container. With DPC_GALLERY__URL=postgresql://... it lives in
# PostgreSQL instead, shared by every replica (deploy/compose.yaml, deploy/k8s/).

ARG PYTHON_IMAGE=python:3.11.14-slim-bookworm
FROM ${PYTHON_IMAGE}

ARG ONNXRUNTIME=onnxruntime
ARG EXTRAS=fast

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

SHELL ["/bin/bash", "-o", "pipefail", "-c"]

# The package with its runtime dependencies (and the fast extra), never torch; numba's compiled
# loops cached in the image, where the service's user may also write them.
ENV NUMBA_CACHE_DIR=/var/cache/numba
COPY pyproject.toml README.md /tmp/src/
COPY service /tmp/src/service
COPY training /tmp/src/training
RUN pip install --no-cache-dir "/tmp/src${EXTRAS:+[${EXTRAS}]}" \
    && rm -rf /tmp/src \
    && mkdir -p "${NUMBA_CACHE_DIR}" \
    && python -c "from service.engine import kernels; kernels.warm(); print(kernels.describe())" \
    && chown -R 10001:10001 "${NUMBA_CACHE_DIR}" \
    && if python -c "import torch" 2>/dev/null; then echo "torch must not be installed" >&2; exit 1; fi

# Optionally the CUDA build of onnxruntime in place of the CPU one.
RUN if [ "${ONNXRUNTIME}" != "onnxruntime" ]; then \
        minor="$(python -c 'import importlib.metadata as m; print(".".join(m.version("onnxruntime").split(".")[:2]))')" \
        && pip uninstall -y onnxruntime \
        && pip install --no-cache-dir "${ONNXRUNTIME}[cuda,cudnn]==${minor}.*" \
        && nvidia="$(python -c 'import site; print(site.getsitepackages()[0])')/nvidia" \
        && if [ -d "${nvidia}" ]; then \
               find "${nvidia}" -type d -name lib > /etc/ld.so.conf.d/nvidia-pip.conf && ldconfig; \
           fi \
        && python -c "import onnxruntime as ort; print(ort.__version__, ort.get_available_providers())"; \
    fi

# A system user that owns nothing but the data volume; the code and the model stay root's.
RUN groupadd --system --gid 10001 dpc \
    && useradd --system --uid 10001 --gid 10001 --no-create-home --home-dir /app \
        --shell /usr/sbin/nologin dpc \
    && mkdir -p /app/models /data \
    && chown 10001:10001 /data

WORKDIR /app
# The release: dpc_mn.onnx, manifest.json (their sha256s), gallery.npz, the sample cloud.
COPY models/ /app/models/

ENV DPC_SERVER__HOST=0.0.0.0 \
    DPC_SERVER__PORT=8000 \
    DPC_MODEL__PATH=/app/models/dpc_mn.onnx \
    DPC_MODEL__GALLERY=/app/models/gallery.npz \
    DPC_GALLERY__DATA_DIR=/data

VOLUME ["/data"]
USER 10001:10001
EXPOSE 8000

# /health is 200 once the model and the gallery are loaded (503 while loading: unhealthy).
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request as u; u.urlopen('http://127.0.0.1:%s/health' % os.environ.get('DPC_SERVER__PORT', '8000'), timeout=4)"]

CMD ["python", "-m", "service"]
