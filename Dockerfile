# threedq on CPU by default; for a GPU image build with
#   docker build --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu128 -t threedq:gpu .
# threedq has no compiled extensions (pure torch + kornia), so there is no CUDA arch list to match.
FROM python:3.11-slim

ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu

# Mesa's EGL (llvmpipe) for the headless offline scene renderer; libgl for moderngl's loader.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1 libgles2 libgbm1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/threedq
RUN pip install --no-cache-dir "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX}"
COPY pyproject.toml README.md ./
COPY threedq ./threedq
COPY datamodules ./datamodules
COPY stages ./stages
COPY configs ./configs
RUN pip install --no-cache-dir ".[test]"
COPY tests ./tests

WORKDIR /work
ENTRYPOINT ["threedq"]
CMD ["--help"]
