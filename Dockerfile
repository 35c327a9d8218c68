# overtake's images, one target each (docker-compose.yml builds both):
#   docker build --target server  -t overtake-server .   simulator, overtake-router, spectators,
#                                                         the Rerun viewer; no PyTorch (1.2 GB,
#                                                         0.65 of it rerun-sdk: viewer, bindings,
#                                                         pyarrow)
#   docker build --target trainer -t overtake-trainer .  overtake-train / overtake-eval with the
#                                                         CPU build of PyTorch 2.13.0 (1.6 GB;
#                                                         no viewer binary, PyTorch's tests or
#                                                         headers: docker/slim.sh)
# The router itself is the official eclipse/zenoh image (see docker-compose.yml).
#
# Building offline or behind a proxy (docs/compose.md): three build arguments and one build secret.
#   BASE_IMAGE       any Debian-like image with Python 3.11 and its venv module: python:3.11-slim
#                    by default, or one made where no registry is reachable
#                    (scripts/make-base-image.sh makes one from Debian's packages)
#   TORCH_WHEEL_DIR  a folder of the build context; a torch 2.13.0 wheel in it is installed
#                    instead of one from TORCH_INDEX_URL (default docker/wheels, which holds
#                    none unless you put one there)
#   TORCH_INDEX_URL  where the trainer image gets PyTorch's CPU wheel otherwise
#   PIP_INDEX_URL    (unset by default) a PyPI mirror for everything else
#   secret pip_ca    a CA bundle that pip trusts, for networks whose proxy re-signs TLS
#                    (docker build --secret id=pip_ca,src=/path/to/ca-bundle.crt ...)
# No `# syntax=` line: it would pull the Dockerfile frontend from a registry; the engine's own
# frontend has the secret and bind mounts used below.
ARG BASE_IMAGE=python:3.11-slim

# The torch wheel folder as a stage of its own, mounted by the trainer stage: a folder named by
# a build argument can be copied but not mounted directly (the engine's own frontend does not
# expand arguments in --mount), and a copy in the trainer stage would stay in a layer.
FROM scratch AS torch-wheels
ARG TORCH_WHEEL_DIR=docker/wheels
COPY ${TORCH_WHEEL_DIR}/ /

FROM ${BASE_IMAGE} AS base
# The venv: one place for overtake whatever the base (a Debian system Python refuses
# `pip install` outside one, PEP 668); its bin first on PATH gives `python` and the commands.
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH
COPY docker/pip-install.sh /usr/local/bin/pip-install
COPY docker/slim.sh /usr/local/bin/slim
# Not root: the processes only need their data directories, created here so that fresh named
# volumes mounted on them inherit the owner.
RUN python3 -m venv /opt/venv \
    && useradd --create-home --uid 10001 overtake \
    && mkdir -p /data/runs /data/recordings \
    && chown -R overtake:overtake /data
WORKDIR /src

FROM base AS server
ARG PIP_INDEX_URL
COPY pyproject.toml README.md LICENSE ./
COPY protocol protocol
COPY envs envs
COPY ipc ipc
COPY cli cli
COPY viz viz
COPY server server
COPY client client
COPY trainers trainers
# `.` alone: the simulator's dependencies (numpy, gymnasium, zenoh, msgpack, rerun-sdk, tyro).
# The train extra (PyTorch) would double the image. pip-install is
# docker/pip-install.sh: pip with the optional CA bundle and index.
RUN --mount=type=secret,id=pip_ca \
    pip-install . \
    && viewer="$(python -c 'import os, rerun_cli; print(os.path.dirname(rerun_cli.__file__))')" \
    && ln -s "$viewer/rerun" /usr/local/bin/rerun-viewer \
    && python -m overtake.server.sim.warm \
    && slim server
# rerun-viewer is the viewer binary itself, not the `rerun` script, which runs it as a child:
# a signal to the container then reaches the viewer. The simulator's numba loops are compiled
# into the image (overtake.server.sim.warm): a container's first decision loads them.
USER overtake
WORKDIR /data
EXPOSE 7447
CMD ["overtake-server", "--listen", "tcp/0.0.0.0:7447"]

FROM base AS trainer
ARG PIP_INDEX_URL
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
# PyTorch's CPU wheel first (from TORCH_WHEEL_DIR, else from TORCH_INDEX_URL alone): `.[train]`
# then finds torch==2.13.0 already satisfied; from PyPI it would bring gigabytes of CUDA
# libraries. A local wheel takes its dependencies (filelock, sympy, ...) from the usual index:
# `--index-url` would replace that index, and where PyTorch's cannot be reached nothing is
# found. Before the sources are copied, so that editing the code does not install PyTorch
# again; the wheel folder is mounted, not copied, so it adds no layer.
RUN --mount=type=secret,id=pip_ca \
    --mount=type=bind,from=torch-wheels,target=/tmp/torch-wheels \
    if ls /tmp/torch-wheels/torch-2.13.0[+-]*.whl >/dev/null 2>&1; then \
        pip-install --find-links /tmp/torch-wheels torch==2.13.0; \
    else \
        pip-install torch==2.13.0 --index-url "$TORCH_INDEX_URL"; \
    fi \
    && slim torch
COPY pyproject.toml README.md LICENSE ./
COPY protocol protocol
COPY envs envs
COPY ipc ipc
COPY cli cli
COPY viz viz
COPY server server
COPY client client
COPY trainers trainers
RUN --mount=type=secret,id=pip_ca \
    pip-install ".[train]" \
    && python -m overtake.server.sim.warm \
    && slim trainer
USER overtake
WORKDIR /data
CMD ["overtake-train", "--help"]
