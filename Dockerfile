# The flextrack backend: the PoseEstimation gRPC server with its light estimators (no torch).
#   docker build -t flextrack-backend .
#   docker run -p 127.0.0.1:50051:50051 flextrack-backend   # unauthenticated: publish it on loopback (CMD below)
ARG BASE_IMAGE=python:3.11-slim

# Stage 1: the wheel, built from the source tree, with the default object generated into it first (it is code,
# not tracked; generating it needs the simulator's numpy, trimesh, scipy and matplotlib, in a throwaway venv), so
# that the object, the shipped model and the default config ride in the wheel as package data.
FROM ${BASE_IMAGE} AS wheel
WORKDIR /src
COPY . /src
RUN python3 -m venv /tmp/gen \
 && /tmp/gen/bin/pip install --no-cache-dir -q numpy trimesh scipy matplotlib \
 && /tmp/gen/bin/python -m flextrack.simulator.default_object --out flextrack/assets/objects/default/models \
 && python3 -m pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

# Stage 2: the backend, installed from that wheel alone: no source tree, no editable install.
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

COPY --from=wheel /wheels /wheels
WORKDIR /wheels
# The built wheel with the backend's extra only; the venv keeps pip off the distribution's own Python
# (PEP 668 on Debian-based images).
RUN python3 -m venv /opt/venv \
 && python -m pip install --no-cache-dir "/wheels/$(echo flextrack-*.whl)[server]" \
 && rm /wheels/*.whl \
 && useradd --create-home --uid 10001 --shell /usr/sbin/nologin flextrack
WORKDIR /app

USER 10001
EXPOSE 50051
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
  CMD ["flextrack", "serve", "--check", "127.0.0.1:50051"]
# Listening on all interfaces without TLS or a token is a deliberate choice here, hence --insecure-public: the
# port is meant to be published to a private network or a mesh that authenticates. On an open network run
# with TLS or tokens instead, e.g. CMD ["flextrack", "serve", "--host", "0.0.0.0", "--token-file", "/run/tokens"].
CMD ["flextrack", "serve", "--host", "0.0.0.0", "--port", "50051", "--insecure-public"]
