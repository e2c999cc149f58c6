"""The deployment files, checked without a cluster: docker/k8s against Kubernetes' own schemas
(kubernetes-validate, strict: an unknown or misspelled field fails), yamllint on every YAML file,
the ConfigMap's radserve.toml accepted by the real server, and the ports, probes and grace periods
of the manifests, the Compose file and the Dockerfile agreeing with each other."""

import copy
import re
import tomllib
from pathlib import Path

import kubernetes_validate
import pytest
import yaml
from yamllint import linter
from yamllint.config import YamlLintConfig

import radserve

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "docker" / "k8s"
COMPOSE = ROOT / "docker" / "compose.yaml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"
KUBERNETES = kubernetes_validate.latest_version()
LINT = YamlLintConfig("extends: default\nrules:\n  line-length: {max: 120}\n  document-start: disable\n"
                      "  comments: {min-spaces-from-content: 1}\n  truthy: {check-keys: false}\n")


def manifests() -> "dict[str, dict]":
    return {path.name: yaml.safe_load(path.read_text()) for path in sorted(K8S.glob("*.yaml"))}


def by_kind(kind: str) -> dict:
    (found,) = [doc for doc in manifests().values() if doc["kind"] == kind]
    return found


def server_config() -> dict:
    return tomllib.loads(by_kind("ConfigMap")["data"]["radserve.toml"])


@pytest.mark.parametrize("name", sorted(path.name for path in K8S.glob("*.yaml")))
def test_manifests_are_valid_kubernetes(name):
    document = manifests()[name]
    if document["kind"] == "Kustomization":
        listed = set(document["resources"])
        assert listed == {path.name for path in K8S.glob("*.yaml")} - {"kustomization.yaml"}
        return
    kubernetes_validate.validate(document, KUBERNETES, strict=True)


@pytest.mark.parametrize("path", [*sorted(K8S.glob("*.yaml")), COMPOSE], ids=lambda p: p.name)
def test_yaml_files_lint_clean(path):
    problems = list(linter.run(path.read_text(), LINT, str(path)))
    assert not problems, "\n".join(f"{path.name}:{p.line}:{p.column} {p.message}" for p in problems)


@pytest.mark.parametrize("field, where", [("readinesProbe", "container"), ("terminationGracePeriod", "pod"),
                                          ("replica", "spec")])
def test_a_misspelled_field_fails_validation(field, where):
    statefulset = copy.deepcopy(by_kind("StatefulSet"))
    target = {"spec": statefulset["spec"], "pod": statefulset["spec"]["template"]["spec"],
              "container": statefulset["spec"]["template"]["spec"]["containers"][0]}[where]
    target[field] = 1
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(statefulset, KUBERNETES, strict=True)


def test_probes_ports_and_names_agree():
    statefulset, service = by_kind("StatefulSet"), by_kind("Service")
    pod = statefulset["spec"]["template"]
    (container,) = pod["spec"]["containers"]
    ports = {port["name"]: port["containerPort"] for port in container["ports"]}
    config = server_config()
    # The server listens where the pod says, and so does its metrics endpoint.
    assert config["server"]["address"] == f"0.0.0.0:{ports['grpc']}"
    assert config["metrics"]["address"] == f"0.0.0.0:{ports['metrics']}"
    assert pod["metadata"]["annotations"]["prometheus.io/port"] == str(ports["metrics"])
    # Every probe asks grpc.health.v1 on the serving port.
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["grpc"]["port"] == ports["grpc"], probe
    # The Service is headless, selects the StatefulSet's pods and names the container's ports.
    assert service["spec"]["clusterIP"] == "None"
    assert statefulset["spec"]["serviceName"] == service["metadata"]["name"]
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    for port in service["spec"]["ports"]:
        assert port["targetPort"] in ports and port["port"] == ports[port["targetPort"]]
    # The PodDisruptionBudget covers those pods.
    assert by_kind("PodDisruptionBudget")["spec"]["selector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    # SIGTERM: the notice and the drain end before the kubelet's SIGKILL.
    server = config["server"]
    assert pod["spec"]["terminationGracePeriodSeconds"] > server["shutdown_notice_s"] + server["drain_timeout_s"]
    # The startup probe waits for the catalog (~15 s) with room: a minute at least.
    startup = container["startupProbe"]
    assert startup["periodSeconds"] * startup["failureThreshold"] >= 60
    # The tokens file the config names is where the Secret is mounted.
    mounts = {mount["name"]: mount["mountPath"] for mount in container["volumeMounts"]}
    assert Path(config["auth"]["tokens_file"]).parent == Path(mounts["tokens"])
    # The learner Job names every server pod by its stable name under the headless Service.
    job = by_kind("Job")
    (learner,) = job["spec"]["template"]["spec"]["containers"]
    address = next(arg for arg in learner["args"] if arg.startswith("--address="))
    pods = [f"{statefulset['metadata']['name']}-{i}.{service['metadata']['name']}:{ports['grpc']}"
            for i in range(statefulset["spec"]["replicas"])]
    assert address == "--address=" + ",".join(pods)


def test_pods_are_locked_down():
    for kind in ("StatefulSet", "Job"):
        pod = by_kind(kind)["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == 10001
        for container in pod["containers"]:
            context = container["securityContext"]
            assert context == {"allowPrivilegeEscalation": False, "readOnlyRootFilesystem": True,
                               "capabilities": {"drop": ["ALL"]}}, (kind, context)
            limits = container["resources"]["limits"]
            assert "memory" in limits, kind
    volumes = {volume["name"]: volume for volume in by_kind("StatefulSet")["spec"]["template"]["spec"]["volumes"]}
    assert volumes["dshm"]["emptyDir"]["medium"] == "Memory"


def test_the_config_map_is_a_config_the_server_accepts(tmp_path):
    """The ConfigMap's radserve.toml starts the real server (where the cluster's paths and addresses
    are swapped for local ones by the server's own RADSERVE__ variables)."""
    config = tmp_path / "radserve.toml"
    config.write_text(by_kind("ConfigMap")["data"]["radserve.toml"])
    tokens = tmp_path / "tokens.toml"
    tokens.write_text('[[principal]]\nname = "learner"\nrole = "user"\ntoken_sha256 = ["' + "0" * 64 + '"]\n')
    server = radserve.LocalServer(env={"RADSERVE__SERVER__ADDRESS": "127.0.0.1:0",
                                       "RADSERVE__METRICS__ADDRESS": "127.0.0.1:0",
                                       "RADSERVE__AUTH__TOKENS_FILE": str(tokens),
                                       "RADSERVE__SIM__WORKERS": "1"})
    server.args += ["--config", str(config)]
    with server:
        assert re.fullmatch(r"127\.0\.0\.1:\d+", server.address)


def test_compose_and_the_image_agree():
    compose = yaml.safe_load(COMPOSE.read_text())
    services = compose["services"]
    servers = [name for name, service in services.items() if service.get("image", "").startswith("radserve:")]
    assert len(servers) == 3
    learner = services["learner"]
    assert learner["depends_on"] == {name: {"condition": "service_healthy"} for name in servers}
    address = next(arg for arg in learner["command"] if arg.startswith("--address="))
    assert address == "--address=" + ",".join(f"{name}:50051" for name in servers)
    assert compose["networks"]["radserve"]["internal"] is True
    dockerfile = DOCKERFILE.read_text()
    assert 'HEALTHCHECK' in dockerfile and 'CMD ["radserve", "healthcheck"]' in dockerfile
    assert "RADSERVE__SERVER__ADDRESS=0.0.0.0:50051" in dockerfile and "EXPOSE 50051 9090" in dockerfile
    assert 'ENTRYPOINT ["radserve"]' in dockerfile and 'CMD ["serve"]' in dockerfile
    # The drain ends within Compose's grace period, as in the pods'.
    grace = int(services[servers[0]]["stop_grace_period"].rstrip("s"))
    assert grace > 1 + 20  # server.shutdown_notice_s + server.drain_timeout_s, the defaults
