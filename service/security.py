"""Transport security and caller authentication for the gRPC server.

Why here and not in the servicer: encryption and "who may call" are properties of the server, not
of pose estimation, so they live beside it as credentials and one interceptor that the server is
built with; the servicer stays unaware of them.

- TLS: certificate and key from PEM files; with a client CA the server also demands and verifies a
  client certificate (mutual TLS).
- Bearer tokens: every call must carry `authorization: Bearer <token>` with one of the configured
  tokens, else it fails with UNAUTHENTICATED before it reaches the servicer. Tokens are compared in
  constant time against all configured tokens (no early exit that would reveal which one nearly
  matched) and are never written to a log or an error message. Health checks stay open so that
  orchestrators (Kubernetes probes) can ask without a secret.
"""

from __future__ import annotations

import hmac
import logging
from collections.abc import Iterable
from pathlib import Path

import grpc

log = logging.getLogger(__name__)

# Methods that need no token: the health service, which probes and load balancers call.
OPEN_METHOD_PREFIXES: tuple[str, ...] = ("/grpc.health.v1.Health/",)
_BEARER = "bearer "


def _read_pem(path: str | Path, what: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read the {what} file {str(path)!r}: {exc.strerror}") from None
    if b"-----BEGIN" not in data:
        raise ValueError(f"the {what} file {str(path)!r} is not PEM (no -----BEGIN line)")
    return data


def server_credentials(cert_file: str | Path, key_file: str | Path,
                       client_ca_file: str | Path | None = None) -> grpc.ServerCredentials:
    """TLS server credentials; with `client_ca_file`, clients must present a certificate it signed."""
    cert = _read_pem(cert_file, "TLS certificate")
    key = _read_pem(key_file, "TLS key")
    ca = _read_pem(client_ca_file, "client CA") if client_ca_file else None
    return grpc.ssl_server_credentials([(key, cert)], root_certificates=ca, require_client_auth=ca is not None)


def load_tokens(path: str | Path) -> list[str]:
    """Tokens from a file, one a line; blank lines and lines starting with '#' are skipped."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read the token file {str(path)!r}: {exc}") from None
    tokens = [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]
    if not tokens:
        raise ValueError(f"the token file {str(path)!r} holds no token")
    if any(any(c.isspace() for c in t) for t in tokens):
        raise ValueError(f"the token file {str(path)!r} has a token with whitespace inside")
    return tokens


class BearerTokenInterceptor(grpc.aio.ServerInterceptor):
    """Refuses every call without a valid bearer token with UNAUTHENTICATED (open methods excepted)."""

    def __init__(self, tokens: Iterable[str], open_prefixes: tuple[str, ...] = OPEN_METHOD_PREFIXES):
        self._tokens = [t.encode("utf-8") for t in tokens]
        if not self._tokens:
            raise ValueError("BearerTokenInterceptor needs at least one token")
        self._open = open_prefixes

    def is_valid(self, authorization: str | bytes | None) -> bool:
        """True when the header is `Bearer <one of the tokens>`; constant time over all tokens."""
        if isinstance(authorization, bytes):
            authorization = authorization.decode("utf-8", "replace")
        if not authorization or authorization[: len(_BEARER)].lower() != _BEARER:
            return False
        offered = authorization[len(_BEARER):].strip().encode("utf-8")
        ok = False
        for token in self._tokens:
            ok |= hmac.compare_digest(offered, token)
        return ok

    async def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method or ""
        if method.startswith(self._open):
            return await continuation(handler_call_details)
        metadata = handler_call_details.invocation_metadata or ()
        authorization = next((v for k, v in metadata if k == "authorization"), None)
        handler = await continuation(handler_call_details)
        if self.is_valid(authorization):
            return handler
        log.info("refused a call to %s: %s bearer token", method, "no" if authorization is None else "invalid")
        return _refusal(handler)


_REFUSAL = "missing or invalid bearer token (send metadata 'authorization: Bearer <token>')"


def _refusal(handler: grpc.RpcMethodHandler | None) -> grpc.RpcMethodHandler | None:
    """A handler of the same streaming shape as `handler` that fails the call with UNAUTHENTICATED."""
    if handler is None:  # unknown method: let gRPC answer UNIMPLEMENTED
        return None

    async def deny(_request, context):
        await context.abort(grpc.StatusCode.UNAUTHENTICATED, _REFUSAL)

    shape = (handler.request_streaming, handler.response_streaming)
    make = {
        (False, False): grpc.unary_unary_rpc_method_handler,
        (False, True): grpc.unary_stream_rpc_method_handler,
        (True, False): grpc.stream_unary_rpc_method_handler,
        (True, True): grpc.stream_stream_rpc_method_handler,
    }[shape]
    # grpc.aio accepts a plain coroutine for every shape (streaming replies go through context.write)
    return make(deny, request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer)
