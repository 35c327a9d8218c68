# syntax=docker/dockerfile:1
# overtake's images, one target each (docker-compose.yml builds both):
#   docker build --target server  -t overtake-server .   simulator, overtake-router, spectators,
#                                                         the Rerun viewer; no PyTorch (~0.3 GB)
#   docker build --target trainer -t overtake-trainer .  overtake-train / overtake-eval with the
#                                                         CPU build of PyTorch 2.13.0
# The router itself is the official eclipse/zenoh image (see docker-compose.yml).

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
# Not root: the processes only need their data directories, created here so that fresh named
# volumes mounted on them inherit the owner.
RUN useradd --create-home --uid 10001 overtake \
    && mkdir -p /data/runs /data/recordings \
    && chown -R overtake:overtake /data
WORKDIR /src

FROM base AS server
COPY pyproject.toml README.md LICENSE ./
COPY protocol protocol
COPY viz viz
COPY server server
COPY client client
COPY trainers trainers
# `.` alone: the simulator's dependencies (numpy, gymnasium, zenoh, msgpack, rerun-sdk, tyro).
# The train extra (PyTorch) is what makes the trainer image ten times larger.
RUN pip install . \
    && viewer="$(python -c 'import os, rerun_cli; print(os.path.dirname(rerun_cli.__file__))')" \
    && ln -s "$viewer/rerun" /usr/local/bin/rerun-viewer
# rerun-viewer is the viewer binary itself, not the `rerun` script, which runs it as a child:
# a signal to the container then reaches the viewer.
USER overtake
WORKDIR /data
EXPOSE 7447
CMD ["overtake-server", "--listen", "tcp/0.0.0.0:7447"]

FROM base AS trainer
# PyTorch's CPU wheel first, from PyTorch's own index: `.[train]` then finds torch==2.13.0
# already satisfied; from PyPI it would bring gigabytes of CUDA libraries. Before the sources
# are copied, so that editing the code does not download PyTorch again.
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md LICENSE ./
COPY protocol protocol
COPY viz viz
COPY server server
COPY client client
COPY trainers trainers
RUN pip install ".[train]"
USER overtake
WORKDIR /data
CMD ["overtake-train", "--help"]
