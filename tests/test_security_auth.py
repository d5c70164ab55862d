"""TLS, mutual TLS and bearer tokens against a real loopback server (certificates made by trustme)."""

from __future__ import annotations

import logging

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from client_sdk import credentials as client_credentials
from estimators.gt_oracle import GtOracleEstimator
from estimators.registry import EstimatorRegistry
from flextrack.testing.toy_sequence import write_orbit_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service import security
from service.hardening import Hardening
from service.server import BackgroundServer

trustme = pytest.importorskip("trustme", reason="trustme (dev extra) makes the test certificates")

TOKEN = "s3cret-token-for-tests"


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    seq = write_orbit_sequence(tmp_path_factory.mktemp("seq") / "orbit", frames=10)
    return EstimatorRegistry([GtOracleEstimator("gt_oracle", [seq.root])]), seq


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A CA with a server and a client certificate, and a second CA nobody trusts."""
    d = tmp_path_factory.mktemp("pki")
    ca, rogue = trustme.CA(), trustme.CA()
    server = ca.issue_cert("localhost", "127.0.0.1")
    files = {"ca": d / "ca.pem", "rogue_ca": d / "rogue_ca.pem", "cert": d / "server.pem", "key": d / "server.key",
             "client_cert": d / "client.pem", "client_key": d / "client.key",
             "rogue_cert": d / "rogue.pem", "rogue_key": d / "rogue.key"}
    ca.cert_pem.write_to_path(files["ca"])
    rogue.cert_pem.write_to_path(files["rogue_ca"])
    server.cert_chain_pems[0].write_to_path(files["cert"])
    server.private_key_pem.write_to_path(files["key"])
    for prefix, authority in (("client", ca), ("rogue", rogue)):
        leaf = authority.issue_cert(f"{prefix}-device@flextrack")
        leaf.cert_chain_pems[0].write_to_path(files[f"{prefix}_cert"])
        leaf.private_key_pem.write_to_path(files[f"{prefix}_key"])
    return files


def _request(seq) -> pb.EstimateRequest:
    return pb.EstimateRequest(frame_id=1, capture_time_ns=int(seq.frame_times_ns[3]))


def _estimate(channel, seq, metadata=()):
    return pb_grpc.PoseEstimationStub(channel).Estimate(_request(seq), timeout=30, metadata=metadata)


def _track(channel, seq, metadata=()):
    return list(pb_grpc.PoseEstimationStub(channel).Track(iter([_request(seq)]), timeout=30, metadata=metadata))


def test_tls_server_answers_a_client_that_trusts_its_ca(registry, pki):
    reg, seq = registry
    with BackgroundServer(reg, grace_s=0.0, hardening=Hardening(tls_cert=pki["cert"], tls_key=pki["key"])) as srv:
        address = srv.address
        with client_credentials.secure_channel(address, root_ca=pki["ca"], server_name="localhost") as channel:
            assert _estimate(channel, seq).status == pb.EstimateResponse.OK
        with client_credentials.secure_channel(address, root_ca=pki["rogue_ca"], server_name="localhost") as channel:
            with pytest.raises(grpc.RpcError) as err:
                _estimate(channel, seq)
            assert err.value.code() == grpc.StatusCode.UNAVAILABLE  # the handshake fails
        with grpc.insecure_channel(address) as channel, pytest.raises(grpc.RpcError):  # plaintext to a TLS port
            _estimate(channel, seq)


def test_mutual_tls_refuses_clients_without_a_certificate_signed_by_the_client_ca(registry, pki):
    reg, seq = registry
    hardening = Hardening(tls_cert=pki["cert"], tls_key=pki["key"], client_ca=pki["ca"])
    with BackgroundServer(reg, grace_s=0.0, hardening=hardening) as srv:
        address = srv.address
        good = client_credentials.secure_channel(address, root_ca=pki["ca"], client_cert=pki["client_cert"],
                                                 client_key=pki["client_key"], server_name="localhost")
        with good as channel:
            assert _estimate(channel, seq).status == pb.EstimateResponse.OK
        for cert, key in ((None, None), (pki["rogue_cert"], pki["rogue_key"])):
            with client_credentials.secure_channel(address, root_ca=pki["ca"], client_cert=cert, client_key=key,
                                                   server_name="localhost") as channel:
                with pytest.raises(grpc.RpcError) as err:
                    _estimate(channel, seq)
                assert err.value.code() == grpc.StatusCode.UNAVAILABLE


def test_token_is_required_on_every_method_but_health(registry, caplog):
    reg, seq = registry
    wrong = "wrong-token-that-must-not-be-logged"
    hardening = Hardening(tokens=[TOKEN])
    with caplog.at_level(logging.DEBUG), BackgroundServer(reg, grace_s=0.0, hardening=hardening) as srv, \
            grpc.insecure_channel(srv.address) as channel:
        stub = pb_grpc.PoseEstimationStub(channel)
        for metadata in ((), client_credentials.token_metadata(wrong), (("authorization", TOKEN),)):
            calls = (lambda md: _estimate(channel, seq, md), lambda md: _track(channel, seq, md),
                     lambda md: stub.ListEstimators(pb.ListEstimatorsRequest(), timeout=30, metadata=md))
            for call in calls:
                with pytest.raises(grpc.RpcError) as err:
                    call(metadata)
                assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
                assert wrong not in err.value.details() and TOKEN not in err.value.details()
        good = client_credentials.token_metadata(TOKEN)
        assert _estimate(channel, seq, good).status == pb.EstimateResponse.OK
        assert [r.status for r in _track(channel, seq, good)] == [pb.EstimateResponse.OK]
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=30)
        assert health.status == health_pb2.HealthCheckResponse.SERVING  # probes need no secret
    assert "refused a call" in caplog.text
    assert wrong not in caplog.text and TOKEN not in caplog.text


def test_token_over_tls_with_sdk_call_credentials(registry, pki):
    reg, seq = registry
    hardening = Hardening(tls_cert=pki["cert"], tls_key=pki["key"], tokens=[TOKEN, "another"])
    with BackgroundServer(reg, grace_s=0.0, hardening=hardening) as srv:
        address = srv.address
        for token, ok in ((TOKEN, True), ("another", True), ("nope", False), (None, False)):
            with client_credentials.secure_channel(address, root_ca=pki["ca"], token=token,
                                                   server_name="localhost") as channel:
                if ok:
                    assert _estimate(channel, seq).status == pb.EstimateResponse.OK
                else:
                    with pytest.raises(grpc.RpcError) as err:
                        _estimate(channel, seq)
                    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED


def test_token_check_accepts_only_exact_bearer_tokens():
    check = security.BearerTokenInterceptor([TOKEN]).is_valid
    assert check(f"Bearer {TOKEN}") and check(f"bearer {TOKEN}") and check(f"Bearer {TOKEN}".encode())
    for bad in (None, "", TOKEN, f"Basic {TOKEN}", f"Bearer {TOKEN}x", f"Bearer {TOKEN[:-1]}", "Bearer ", "Bearer"):
        assert not check(bad), bad


def test_token_file_and_certificate_errors_are_clear(tmp_path):
    (tmp_path / "tokens").write_text("# comment\n\n  abc  \ndef\n")
    assert security.load_tokens(tmp_path / "tokens") == ["abc", "def"]
    (tmp_path / "empty").write_text("# nothing\n")
    with pytest.raises(ValueError, match="holds no token"):
        security.load_tokens(tmp_path / "empty")
    with pytest.raises(ValueError, match="cannot read the token file"):
        security.load_tokens(tmp_path / "missing")
    (tmp_path / "cert.pem").write_text("not a certificate")
    with pytest.raises(ValueError, match="not PEM"):
        security.server_credentials(tmp_path / "cert.pem", tmp_path / "cert.pem")
    with pytest.raises(ValueError, match="cannot read the TLS certificate"):
        security.server_credentials(tmp_path / "none.pem", tmp_path / "none.key")
    with pytest.raises(ValueError, match="both client_cert and client_key"):
        client_credentials.tls_credentials(client_cert=tmp_path / "cert.pem")
    with pytest.raises(ValueError, match="bearer token"):
        client_credentials.token_metadata("two words")


def test_serve_flags_are_checked_before_serving(tmp_path, pki):
    import argparse

    from service import hardening

    parser = argparse.ArgumentParser()
    hardening.add_arguments(parser)

    def build(*flags):
        return hardening.Hardening.from_args(parser.parse_args(list(flags)))

    plain = build()
    assert plain.credentials() is None and [type(i).__name__ for i in plain.interceptors()] == ["AdmissionInterceptor"]
    (tmp_path / "tokens").write_text(f"{TOKEN}\n")
    secured = build("--tls-cert", str(pki["cert"]), "--tls-key", str(pki["key"]), "--client-ca", str(pki["ca"]),
                    "--token-file", str(tmp_path / "tokens"), "--max-queue", "4", "--max-streams", "9")
    assert secured.credentials() is not None
    assert [type(i).__name__ for i in secured.interceptors()] == ["BearerTokenInterceptor", "AdmissionInterceptor"]
    assert (secured.admission.max_queue, secured.admission.max_streams) == (4, 9)
    for flags, message in ((["--tls-cert", str(pki["cert"])], "both --tls-cert and --tls-key"),
                           (["--client-ca", str(pki["ca"])], "needs --tls-cert"),
                           (["--tls-cert", str(tmp_path / "no.pem"), "--tls-key", str(pki["key"])], "cannot read"),
                           (["--token-file", str(tmp_path / "none")], "cannot read the token file"),
                           (["--max-queue", "-1"], "max_queue"), (["--max-batch", "0"], "max-batch")):
        with pytest.raises(ValueError, match=message):
            build(*flags)
    assert build("--max-batch", "4").workers(2) == 8 and plain.workers(3) == 3


def test_track_client_streams_over_tls_with_a_token(registry, pki):
    import queue

    from client_sdk.transport import TrackClient, TransportOptions, make_request

    reg, seq = registry
    hardening = Hardening(tls_cert=pki["cert"], tls_key=pki["key"], tokens=[TOKEN])
    answers: queue.Queue = queue.Queue()
    creds = client_credentials.channel_credentials(pki["ca"], token=TOKEN)
    with BackgroundServer(reg, grace_s=0.0, hardening=hardening) as srv, \
            TrackClient(srv.address, answers.put, lambda frame_id, why: answers.put(why), credentials=creds,
                        options=TransportOptions(connect_timeout_s=2.0)) as client:
        assert client.wait_connected(5)
        assert client.submit(make_request(frame_id=3, capture_time_ns=int(seq.frame_times_ns[3])))
        answer = answers.get(timeout=10)
    assert answer.status == pb.EstimateResponse.OK and answer.frame_id == 3, answer
