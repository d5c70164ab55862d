"""The Kubernetes manifests in deploy/k8s: schema-valid (kubernetes-validate ships the OpenAPI schemas,
so this runs offline) and wired together (probes on the gRPC health service, a headless Service that
selects the Deployment's pods, an autoscaler on that Deployment, flags the server really has)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

kubernetes_validate = pytest.importorskip("kubernetes_validate",
                                          reason="kubernetes-validate (dev extra) is not installed")

K8S = Path(__file__).resolve().parents[1] / "deploy" / "k8s"
VERSION = "1.30.0"  # the oldest release we claim: gRPC probes are GA since 1.27, autoscaling/v2 since 1.23


def _docs(name: str) -> list[dict]:
    return [d for d in yaml.safe_load_all((K8S / name).read_text()) if d]


def _by_kind() -> dict[str, dict]:
    kustomization = _docs("kustomization.yaml")[0]
    return {d["kind"]: d for name in kustomization["resources"] for d in _docs(name)}


@pytest.mark.parametrize("name", sorted(p.name for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml"))
def test_manifest_is_schema_valid(name):
    for doc in _docs(name):
        kubernetes_validate.validate(doc, VERSION, strict=True)


def test_validator_rejects_a_misspelt_field():
    deployment = _by_kind()["Deployment"]
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    container["readinessProbes"] = container.pop("readinessProbe")
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, VERSION, strict=True)


def test_probes_use_grpc_health_on_the_served_port():
    container = _by_kind()["Deployment"]["spec"]["template"]["spec"]["containers"][0]
    grpc_port = next(p["containerPort"] for p in container["ports"] if p["name"] == "grpc")
    assert f"--port={grpc_port}" in container["args"]
    for probe in ("livenessProbe", "readinessProbe"):
        assert container[probe]["grpc"]["port"] == grpc_port
    assert container["readinessProbe"]["grpc"]["service"] == "flextrack.v1.PoseEstimation"
    assert container["resources"]["requests"]["cpu"] and container["resources"]["requests"]["memory"]
    assert container["resources"]["limits"]["cpu"] and container["resources"]["limits"]["memory"]


def test_headless_service_and_autoscaler_point_at_the_deployment():
    kinds = _by_kind()
    deployment, service, hpa = kinds["Deployment"], kinds["Service"], kinds["HorizontalPodAutoscaler"]
    pod_labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["clusterIP"] == "None"  # headless: DNS lists every pod for round_robin
    assert all(pod_labels.get(k) == v for k, v in service["spec"]["selector"].items())
    assert deployment["spec"]["selector"]["matchLabels"].items() <= pod_labels.items()
    target = hpa["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", deployment["metadata"]["name"])
    assert 1 <= hpa["spec"]["minReplicas"] <= hpa["spec"]["maxReplicas"]


def test_container_args_are_flags_the_server_accepts():
    service_cli = pytest.importorskip("service.cli", reason="service.cli is not there yet")
    import argparse

    parser = argparse.ArgumentParser()
    service_cli.add_arguments(parser)
    args = _by_kind()["Deployment"]["spec"]["template"]["spec"]["containers"][0]["args"]
    assert args[0] == "serve"
    parser.parse_args(args[1:])  # exits (SystemExit) on an unknown flag


def test_public_bind_is_authenticated_and_the_grace_period_covers_drain_and_grace():
    service_cli = pytest.importorskip("service.cli", reason="service.cli is not there yet")
    import argparse

    parser = argparse.ArgumentParser()
    service_cli.add_arguments(parser)
    pod = _by_kind()["Deployment"]["spec"]["template"]["spec"]
    args = parser.parse_args(pod["containers"][0]["args"][1:])
    # `flextrack serve` refuses a non-loopback address without TLS or tokens unless told --insecure-public
    assert service_cli.is_loopback(args.host) or args.token_file or args.tls_cert or args.insecure_public
    assert args.token_file and not args.insecure_public  # here: callers carry a token
    # SIGTERM: NOT_SERVING for --drain-s (readiness must fail within it), then --grace-s for in-flight calls
    readiness = pod["containers"][0]["readinessProbe"]
    assert args.drain_s >= readiness["periodSeconds"] * readiness["failureThreshold"]
    assert pod["terminationGracePeriodSeconds"] >= args.drain_s + args.grace_s
    assert args.metrics_host == "0.0.0.0"  # Prometheus scrapes the pod's address: said explicitly
