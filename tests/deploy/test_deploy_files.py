"""The deployment files hold together: the scale-out compose file, its nginx configuration and the
Kubernetes sketch (Docker and kubectl are not available in CI, so their structure is checked here)."""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
SCALE = ROOT / "docker" / "compose.scale.yaml"
NGINX = ROOT / "docker" / "scale" / "nginx.conf"
KUBERNETES = ROOT / "docs" / "kubernetes.md"
CLUSTER = ROOT / "docker" / "k8s" / "redis-cluster.yaml"


def _services() -> dict:
    return yaml.safe_load(SCALE.read_text())["services"]


def _replicas(services: dict) -> dict[str, dict]:
    """The service replicas: the edgepos image serving (a healthcheck), not the one-shot keygen."""
    return {
        name: s for name, s in services.items() if s.get("image") == "edgepos:latest" and "healthcheck" in s
    }


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
        assert environment["EDGEPOS_ADMIN_KEY"] == "${EDGEPOS_ADMIN_KEY:-}"  # optional: keygen's otherwise
        assert service["depends_on"]["keygen"]["condition"] == "service_completed_successfully"
        assert any(volume.startswith(f"admin-key:{KEY_DIR}:") for volume in service["volumes"])
        assert "/readyz" in " ".join(service["healthcheck"]["test"])
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"


KEY_DIR = "/run/edgepos-key"


def test_scale_compose_runs_as_written_without_an_admin_key() -> None:
    """`docker compose -f docker/compose.scale.yaml up` with no variable set: nothing aborts (no ${VAR:?...})
    and keygen writes the shared key to the volume the replicas read."""
    text = SCALE.read_text()
    assert ":?" not in text
    assert "docker compose -f docker/compose.scale.yaml up --build" in text
    keygen = _services()["keygen"]
    assert keygen["image"] == "edgepos:latest" and keygen["build"]["dockerfile"] == "docker/Dockerfile"
    assert f"admin-key:{KEY_DIR}" in keygen["volumes"]
    assert "admin-key" in yaml.safe_load(text)["volumes"]


def _keygen(directory: Path, environment: dict[str, str]) -> str:
    """keygen's script run here, on ``directory`` instead of the volume; its output."""
    script = _services()["keygen"]["command"][2].replace(KEY_DIR, str(directory))
    if os.geteuid() != 0:  # the chown to the image's user needs root, as keygen runs in compose
        script = script.replace("os.chown(path, 10001, 10001)", "None")
    done = subprocess.run(
        [sys.executable, "-c", script], env=environment, capture_output=True, text=True, check=True
    )
    return done.stdout


def _replica_key(directory: Path, environment: dict[str, str]) -> str:
    """The EDGEPOS_ADMIN_KEY a replica's command hands to edgepos serve (compose's $$ read as $)."""
    command = _replicas(_services())["edgepos-1"]["command"]
    assert command[:2] == ["sh", "-c"] and command[2].endswith("exec edgepos serve --host 0.0.0.0")
    script = command[2].replace("$$", "$").replace(KEY_DIR, str(directory))
    script = script.replace("exec edgepos serve --host 0.0.0.0", "exec printenv EDGEPOS_ADMIN_KEY")
    return subprocess.run(
        ["sh", "-c", script], env=environment, capture_output=True, text=True, check=True
    ).stdout


def test_keygen_generates_one_key_once_and_every_replica_uses_it(tmp_path: Path) -> None:
    environment = {"PATH": os.environ["PATH"], "EDGEPOS_ADMIN_KEY": ""}
    first = _keygen(tmp_path, environment)
    key = (tmp_path / "admin.key").read_text()
    assert len(key) >= 32 and key in first
    assert stat.S_IMODE((tmp_path / "admin.key").stat().st_mode) == 0o600
    assert _keygen(tmp_path, environment) and (tmp_path / "admin.key").read_text() == key  # kept on restart
    assert _replica_key(tmp_path, environment).strip() == key


def test_an_admin_key_set_in_the_shell_wins_over_keygen(tmp_path: Path) -> None:
    environment = {"PATH": os.environ["PATH"], "EDGEPOS_ADMIN_KEY": "chosen-admin-key-0123456789abcdef"}
    assert "as set" in _keygen(tmp_path, environment)
    assert not (tmp_path / "admin.key").exists()
    assert _replica_key(tmp_path, environment).strip() == "chosen-admin-key-0123456789abcdef"


DOCKERFILE = ROOT / "docker" / "Dockerfile"


def test_every_deployment_file_serves_on_port_8000() -> None:
    """The image, both compose files, nginx and the manifests use the port the docs and edgepos serve use."""
    dockerfile = DOCKERFILE.read_text()
    assert re.search(r"^EXPOSE 8000$", dockerfile, re.MULTILINE)
    assert "EDGEPOS_PORT=8000" in dockerfile
    single = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())["services"]["edgepos"]
    assert single["ports"] == ["8000:8000"]
    assert _services()["lb"]["ports"] == ["8000:8000"]
    assert re.search(r"listen 8000;", NGINX.read_text())
    for path in (DOCKERFILE, SCALE, NGINX, ROOT / "docker" / "compose.yaml", CLUSTER, KUBERNETES):
        assert not re.search(r"\b(8080|8765)\b", path.read_text()), path
    assert not re.search(r"\b(8080|8765)\b", (ROOT / "docs" / "service.md").read_text())


def test_the_single_box_docker_line_is_documented() -> None:
    line = "docker build -t edgepos -f docker/Dockerfile . && docker run -p 8000:8000 edgepos"
    assert line in KUBERNETES.read_text()
    assert line in DOCKERFILE.read_text()


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
