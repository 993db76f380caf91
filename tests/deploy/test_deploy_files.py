"""The deployment files hold together: the scale-out compose file, its nginx configuration and the
Kubernetes sketch (Docker and kubectl are not available in CI, so their structure is checked here)."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
SCALE = ROOT / "docker" / "compose.scale.yaml"
NGINX = ROOT / "docker" / "scale" / "nginx.conf"
KUBERNETES = ROOT / "docs" / "kubernetes.md"


def _services() -> dict:
    return yaml.safe_load(SCALE.read_text())["services"]


def _replicas(services: dict) -> dict[str, dict]:
    return {name: s for name, s in services.items() if s.get("image") == "edgepos:latest"}


def test_redis_keeps_an_append_only_file_on_a_volume_and_never_evicts() -> None:
    redis = _services()["redis"]
    command = redis["command"]
    assert command[command.index("--appendonly") + 1] == "yes"
    assert command[command.index("--appendfsync") + 1] in ("everysec", "always")
    assert command[command.index("--maxmemory-policy") + 1] == "noeviction"
    assert any(volume.endswith(":/data") for volume in redis["volumes"])


def test_at_least_two_replicas_share_redis_and_one_admin_key() -> None:
    replicas = _replicas(_services())
    assert len(replicas) >= 2
    for service in replicas.values():
        environment = service["environment"]
        assert environment["EDGEPOS_STORE"].startswith("redis://redis:6379/")
        assert environment["EDGEPOS_ADMIN_KEY"].startswith("${EDGEPOS_ADMIN_KEY:?")  # required, not generated
        assert "/readyz" in " ".join(service["healthcheck"]["test"])
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"


def test_the_load_balancer_sends_to_every_replica_and_nothing_else() -> None:
    services = _services()
    replicas = _replicas(services)
    text = NGINX.read_text()
    assert text.count("{") == text.count("}")
    upstream = re.search(r"upstream edgepos \{(.*?)\}", text, re.DOTALL)
    assert upstream is not None
    servers = re.findall(r"server\s+([\w.-]+):(\d+)", upstream.group(1))
    assert sorted(name for name, _ in servers) == sorted(replicas)
    assert {port for _, port in servers} == {
        service["environment"]["EDGEPOS_PORT"] for service in replicas.values()
    }
    lb = services["lb"]
    assert any(volume.startswith("./scale/nginx.conf:") for volume in lb["volumes"])
    assert set(lb["depends_on"]) == set(replicas)
    # a POST (session creation) must never be sent twice
    assert not re.search(r"proxy_next_upstream[^;]*non_idempotent", text)


def test_kubernetes_sketch_parses_and_probes_readiness() -> None:
    blocks = re.findall(r"```yaml\n(.*?)```", KUBERNETES.read_text(), re.DOTALL)
    documents = [doc for block in blocks for doc in yaml.safe_load_all(block)]
    kinds = {doc["kind"]: doc for doc in documents}
    assert {"Secret", "StatefulSet", "Deployment", "Service"} <= set(kinds)
    deployment = kinds["Deployment"]
    assert deployment["spec"]["replicas"] >= 2
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    environment = {item["name"]: item for item in container["env"]}
    assert environment["EDGEPOS_STORE"]["value"].startswith("redis://edgepos-redis:6379/")
    assert "secretKeyRef" in environment["EDGEPOS_ADMIN_KEY"]["valueFrom"]
    redis = kinds["StatefulSet"]["spec"]["template"]["spec"]["containers"][0]
    assert redis["args"][redis["args"].index("--appendonly") + 1] == "yes"


CLUSTER = ROOT / "docker" / "k8s" / "redis-cluster.yaml"


def test_kubernetes_redis_cluster_manifests_hold_together() -> None:
    from edgepos.store.redis_cluster import parse_cluster_url

    documents = list(yaml.safe_load_all(CLUSTER.read_text()))
    kinds = {doc["kind"]: doc for doc in documents}
    assert {"Service", "StatefulSet", "Job", "Deployment"} <= set(kinds)
    nodes = kinds["StatefulSet"]
    service = kinds["Service"]
    assert (
        service["spec"]["clusterIP"] == "None" and nodes["spec"]["serviceName"] == service["metadata"]["name"]
    )
    assert nodes["spec"]["replicas"] == 6
    args = nodes["spec"]["template"]["spec"]["containers"][0]["args"]
    for flag, value in (
        ("--cluster-enabled", "yes"),
        ("--appendonly", "yes"),
        ("--maxmemory-policy", "noeviction"),
    ):
        assert args[args.index(flag) + 1] == value
    assert args[args.index("--cluster-config-file") + 1].startswith("/data/")  # on the volume
    pods = {f"{nodes['metadata']['name']}-{i}.{service['metadata']['name']}:6379" for i in range(6)}
    create = kinds["Job"]["spec"]["template"]["spec"]["containers"][0]["command"]
    assert create[:3] == ["redis-cli", "--cluster", "create"]
    assert set(create[3:9]) == pods and create[create.index("--cluster-replicas") + 1] == "1"
    container = kinds["Deployment"]["spec"]["template"]["spec"]["containers"][0]
    environment = {item["name"]: item for item in container["env"]}
    parsed = parse_cluster_url(environment["EDGEPOS_STORE"]["value"])
    assert {f"{host}:{port}" for host, port in parsed["nodes"]} <= pods
    assert int(environment["EDGEPOS_REDIS_WAIT_REPLICAS"]["value"]) >= 1
