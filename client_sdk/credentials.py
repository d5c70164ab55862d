"""Client-side TLS and bearer-token credentials for talking to a secured backend.

The server (service.security) may demand TLS, a client certificate (mutual TLS) and a bearer token.
These helpers turn PEM files and a token into the channel a `TrackClient` uses; they need grpcio
only, so they run on a device.
"""

from __future__ import annotations

from pathlib import Path

import grpc


def _read(path: str | Path | None, what: str) -> bytes | None:
    if path is None:
        return None
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read the {what} file {str(path)!r}: {exc.strerror}") from None


def tls_credentials(root_ca: str | Path | None = None, client_cert: str | Path | None = None,
                    client_key: str | Path | None = None) -> grpc.ChannelCredentials:
    """TLS channel credentials. `root_ca` None trusts the system roots; cert + key enable mutual TLS."""
    if (client_cert is None) != (client_key is None):
        raise ValueError("mutual TLS needs both client_cert and client_key")
    return grpc.ssl_channel_credentials(root_certificates=_read(root_ca, "root CA"),
                                        private_key=_read(client_key, "client key"),
                                        certificate_chain=_read(client_cert, "client certificate"))


def token_credentials(token: str) -> grpc.CallCredentials:
    """Call credentials that send `authorization: Bearer <token>` with every call."""
    if not token or any(c.isspace() for c in token):
        raise ValueError("a bearer token must be non-empty and hold no whitespace")
    return grpc.access_token_call_credentials(token)


def channel_credentials(root_ca: str | Path | None = None, client_cert: str | Path | None = None,
                        client_key: str | Path | None = None, token: str | None = None) -> grpc.ChannelCredentials:
    """TLS credentials, with the token attached to every call when one is given."""
    creds = tls_credentials(root_ca, client_cert, client_key)
    return grpc.composite_channel_credentials(creds, token_credentials(token)) if token else creds


def token_metadata(token: str) -> tuple[tuple[str, str], ...]:
    """The same header as plain call metadata, for a channel without TLS (loopback, or TLS ended by a proxy).

    gRPC refuses call credentials on an insecure channel, so there the token travels as metadata.
    """
    if not token or any(c.isspace() for c in token):
        raise ValueError("a bearer token must be non-empty and hold no whitespace")
    return (("authorization", f"Bearer {token}"),)


def secure_channel(target: str, *, root_ca: str | Path | None = None, client_cert: str | Path | None = None,
                   client_key: str | Path | None = None, token: str | None = None,
                   server_name: str | None = None, options: list[tuple[str, object]] | None = None,
                   aio: bool = False):
    """A TLS channel (grpc or grpc.aio) to `target`; `server_name` overrides the name checked in the certificate."""
    opts = list(options or [])
    if server_name:
        opts.append(("grpc.ssl_target_name_override", server_name))
    creds = channel_credentials(root_ca, client_cert, client_key, token)
    return (grpc.aio.secure_channel if aio else grpc.secure_channel)(target, creds, options=opts)
