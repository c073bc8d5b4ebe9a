# threedq in a container: the package installed from its wheel, the tests beside it.
#
#   docker build -t threedq:cpu .                                   # CPU torch from PyTorch's CPU index
#   docker build --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cu128 -t threedq:gpu .   # a GPU image
#   docker run --rm -v "$PWD:/work" threedq:cpu em --rounds 4       # the main job, writing runs/ and data/ here
#   docker run --rm --entrypoint pytest threedq:cpu -m "not slow"   # the tests, from the image
#
# The GPU image is this file with another torch index (threedq has no compiled extensions: pure torch + kornia,
# no CUDA arch list to match); run it with `docker run --gpus all` and `--extra_configs trainer/gpu.yaml`.
# BASE_IMAGE: any Debian-like image with python3 (>= 3.10) and its venv module; scripts/docker_check.sh builds one
# locally for machines without a registry, and a torch index served on the host's loopback (build with
# `--network host`).
ARG BASE_IMAGE=python:3.11-slim

# ---- the wheel: built from the package folders only (setup.py finds the packages) ----
FROM ${BASE_IMAGE} AS wheel
WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY threedq ./threedq
COPY stages ./stages
COPY datamodules ./datamodules
COPY configs ./configs
RUN python3 -m venv /opt/build \
    && /opt/build/bin/pip install --no-cache-dir --disable-pip-version-check -q "setuptools>=70.1" \
    && /opt/build/bin/pip wheel --no-cache-dir --disable-pip-version-check --no-deps --no-build-isolation -w /dist .

# ---- the image: torch, the wheel with its test extra, the tests ----
FROM ${BASE_IMAGE}
ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu

# Mesa's EGL (llvmpipe) for the headless offline scene renderer; libgl for moderngl's loader.
RUN apt-get update \
    && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1 libgles2 libgbm1 \
    && rm -rf /var/lib/apt/lists/*

# A virtual environment: the same on python:3.11-slim and on a distribution python that refuses system-wide pip.
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH PIP_DISABLE_PIP_VERSION_CHECK=1
RUN pip install --no-cache-dir "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX}"
COPY --from=wheel /dist /tmp/dist
RUN pip install --no-cache-dir "$(ls /tmp/dist/threedq-*.whl)[test]" && rm -rf /tmp/dist

# The working folder holds the tests and the files they read (README, Dockerfile, benchmarks, docs), not the package
# sources: the tests import the installed package, which no copy of the source tree can shadow, and `pytest` finds
# them from here. Mount a folder of your own on /work for runs (`-v "$PWD:/work"`): runs/ and data/ land there.
WORKDIR /work
COPY pyproject.toml README.md Dockerfile ./
COPY .ci ./.ci
COPY tests ./tests
COPY benchmarks ./benchmarks
COPY docs ./docs

ENTRYPOINT ["threedq"]
CMD ["--help"]
