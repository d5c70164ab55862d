# The flextrack backend: the PoseEstimation gRPC server with its light estimators (no torch).
#   docker build -t flextrack-backend .
#   docker run -p 50051:50051 flextrack-backend
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

WORKDIR /app
COPY . /app
# The install CI uses (a venv, then pip install -e), with the backend's extra only; the venv also keeps
# pip off the distribution's own Python (PEP 668 on Debian-based images).
RUN python3 -m venv /opt/venv \
 && python -m pip install --no-cache-dir -e '.[server]' \
 && useradd --create-home --uid 10001 --shell /usr/sbin/nologin flextrack

USER 10001
EXPOSE 50051
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
  CMD ["flextrack", "serve", "--check", "127.0.0.1:50051"]
CMD ["flextrack", "serve", "--host", "0.0.0.0", "--port", "50051"]
