"""An nginx in front of a server, as the gate that refuses devices past a bound on open streams.

Why: `flextrack serve --max-streams` refuses a device on the server's own asyncio loop, which
accepts new calls one at a time between the admitted streams' frames; at the oracle's capacity a
refusal waited there for tens to hundreds of ms (docs/operations.md). nginx counts concurrent
requests per key with `limit_conn`, and in HTTP/2 each stream is a request, so it bounds open
`Track` streams and answers the excess itself, in C, before the Python process sees them: with
gRPC's trailers-only form (HTTP 204, `grpc-status` 8 = RESOURCE_EXHAUSTED) and a retry pushback
jittered over 1-3 s by the request id, as the server's own refusal carries (2 s +-50 %). Everything else
(other RPCs, health checks) passes through unbounded. nginx must be installed (Debian: nginx-light);
benchmarks only, not part of the service.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

from flextrack.loadtest import servers

TRACK_PATH = "/flextrack.v1.PoseEstimation/Track"

CONFIG = """daemon off;
master_process off;
worker_processes 1;
pid {workdir}/nginx.pid;
error_log {workdir}/error.log warn;
events {{ worker_connections 8192; }}
http {{
    access_log off;
    client_body_temp_path {workdir}/body;
    client_max_body_size 0;
    limit_conn_zone $server_port zone=streams:1m;  # one key for the whole server (an empty key is not counted)
    map $request_id $pushback_ms {{ ~^[0-3] 1000; ~^[4-7] 1700; ~^[89ab] 2300; default 3000; }}
    upstream backend {{ server {upstream}; keepalive 1024; }}
    server {{
        listen 127.0.0.1:{port} http2;
        http2_max_concurrent_streams 1024;
        location {track_path} {{
            {limit}
            limit_conn_status 429;
            error_page 429 = @exhausted;
            grpc_pass grpc://backend;
            grpc_read_timeout 3600s;
            grpc_send_timeout 3600s;
        }}
        location / {{ grpc_pass grpc://backend; }}
        location @exhausted {{
            default_type application/grpc;
            add_header grpc-status 8 always;
            add_header grpc-message "at the device limit (front proxy)" always;
            add_header grpc-retry-pushback-ms $pushback_ms always;
            return 204;
        }}
    }}
}}
"""


def render_config(upstream: str, port: int, max_streams: int | None, workdir: Path) -> str:
    """The nginx configuration: `max_streams` open Track streams at most (None: no bound)."""
    limit = f"limit_conn streams {max_streams};" if max_streams else "# no bound on streams"
    return CONFIG.format(workdir=workdir, upstream=upstream, port=port, track_path=TRACK_PATH, limit=limit)


def nginx_binary() -> str | None:
    """nginx's path (on PATH, or Debian's /usr/sbin, which is not on every user's PATH), or None."""
    return shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").is_file() else None)


def start_nginx(upstream: str, max_streams: int | None, workdir: Path, cpus: set[int] | None = None,
                nice: int = 0, timeout_s: float = 10.0) -> servers.ServerProcess:
    """nginx listening on a free loopback port in front of `upstream` (host:port), returned once it
    accepts connections. `nice` < 0 (root only) schedules it ahead of a server sharing its CPU."""
    binary = nginx_binary()
    if binary is None:
        raise FileNotFoundError("nginx is not installed (Debian: apt-get install nginx-light); --front nginx needs it")
    workdir.mkdir(parents=True, exist_ok=True)
    port = servers.free_port()
    config = workdir / "nginx.conf"
    config.write_text(render_config(upstream, port, max_streams, workdir.resolve()))
    with open(workdir / "nginx.out", "ab") as log:
        process = subprocess.Popen([binary, "-c", str(config.resolve())], stdout=log, stderr=log)
    proxy = servers.ServerProcess("nginx", f"127.0.0.1:{port}", process)
    servers.pin(process.pid, cpus)
    if nice:
        os.setpriority(os.PRIO_PROCESS, process.pid, nice)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"nginx exited with code {process.returncode}: {(workdir / 'nginx.out').read_text()[-500:]}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return proxy
        except OSError:
            time.sleep(0.05)
    proxy.stop()
    raise TimeoutError(f"nginx did not listen on port {port} within {timeout_s:g} s")
