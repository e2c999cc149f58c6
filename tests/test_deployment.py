"""The deployment files, checked without a cluster: every kustomize overlay of docker/k8s rendered
(kubectl's kustomize) and held to Kubernetes' own schemas (kubernetes-validate, strict: an unknown or
misspelled field fails), read whole by the Docker harness (tests/k8s_harness.py: a field it does not
know fails), yamllint on every YAML file, the ConfigMap's radserve.toml accepted by the real server,
the NetworkPolicy evaluated, and the ports, probes and grace periods of the manifests, the Compose
file and the Dockerfile agreeing with each other. tests/cluster/test_k8s.py runs the overlays."""

import copy
import re
import shutil
import tomllib
from pathlib import Path

import kubernetes_validate
import pytest
import yaml
from yamllint import linter
from yamllint.config import YamlLintConfig

import k8s_harness as harness
import radserve
from radserve.server import find_binary

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "docker" / "k8s"
COMPOSE = ROOT / "docker" / "compose.yaml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"
KUBERNETES = kubernetes_validate.latest_version()
LINT = YamlLintConfig("extends: default\nrules:\n  line-length: {max: 120}\n  document-start: disable\n"
                      "  comments: {min-spaces-from-content: 1}\n  truthy: {check-keys: false}\n")
CERT_MANAGER = {"Certificate", "Issuer"}
VERSION = tomllib.loads((ROOT / "Cargo.toml").read_text())["workspace"]["package"]["version"]


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """docker/k8s with the token and certificate files made as the runbook makes them."""
    return harness.prepare(tmp_path_factory.mktemp("k8s"), [find_binary(), "token"])


@pytest.fixture(scope="module")
def rendered(tree):
    return {overlay: harness.overlay_documents(tree, overlay) for overlay in harness.OVERLAYS}


def one(documents, kind: str) -> dict:
    (found,) = [doc for doc in documents if doc["kind"] == kind]
    return found


def server_container(documents) -> dict:
    (container,) = one(documents, "StatefulSet")["spec"]["template"]["spec"]["containers"]
    return container


def learner_container(documents) -> dict:
    (container,) = one(documents, "Job")["spec"]["template"]["spec"]["containers"]
    return container


def environment(container) -> dict:
    return {entry["name"]: entry.get("value") for entry in container.get("env", [])}


def server_config(documents) -> dict:
    """radserve.toml from the ConfigMap with the container's RADSERVE__SECTION__KEY variables on top."""
    config = tomllib.loads(one(documents, "ConfigMap")["data"]["radserve.toml"])
    for name, value in environment(server_container(documents)).items():
        if name.startswith("RADSERVE__"):
            section, key = name.removeprefix("RADSERVE__").lower().split("__")
            config.setdefault(section, {})[key] = value
    return config


@pytest.mark.parametrize("overlay", harness.OVERLAYS)
def test_overlays_render_to_valid_kubernetes(rendered, overlay):
    documents = rendered[overlay]
    kinds = sorted(doc["kind"] for doc in documents)
    for document in documents:
        if document["kind"] not in CERT_MANAGER:  # cert-manager's CRDs: read field by field by the harness
            kubernetes_validate.validate(document, KUBERNETES, strict=True)
        assert document["metadata"]["namespace"] == "radserve", document["metadata"]["name"]
    assert {"ConfigMap", "Service", "StatefulSet", "Job", "PodDisruptionBudget", "NetworkPolicy",
            "PersistentVolumeClaim"} <= set(kinds)
    assert ("Certificate" in kinds) == (overlay in ("tls", "gpu-learner"))
    # The namespace is applied on its own, first, and no overlay deletes it (docs/deployment.md).
    assert "Namespace" not in kinds
    kubernetes_validate.validate(yaml.safe_load((K8S / "namespace.yaml").read_text()), KUBERNETES, strict=True)


@pytest.mark.parametrize("overlay", harness.OVERLAYS)
def test_the_harness_reads_every_field(rendered, tree, overlay, tmp_path):
    """Every overlay, with and without the short run, translates into docker runs field by field."""
    for short in (False, True):
        documents = harness.overlay_documents(tree, overlay, short_run=short) if short else rendered[overlay]
        cluster = harness.Cluster(documents, tmp_path, "t", harness.namespace_labels())
        assert [pod.name for pod in cluster.pods] == ["radserve-0", "radserve-1", "radserve-2"]
        learner = cluster.jobs["radserve-learner"]["pod"]
        assert learner.gpus == (1 if overlay == "gpu-learner" else 0)
        assert ("--total-env-steps=100000" in learner.argv) == (not short and overlay != "dev")
        server = cluster.pods[0]
        assert "--read-only" in server.run_args and ["--cap-drop", "ALL"] == server.run_args[
            server.run_args.index("--cap-drop"):server.run_args.index("--cap-drop") + 2]
        assert "--network-alias" in server.run_args and "radserve-0.radserve" in server.run_args


@pytest.mark.parametrize("where, field, value", [
    ("pod", "hostNetwork", True), ("container", "lifecycle", {"preStop": {"exec": {"command": ["sleep", "5"]}}}),
    ("container", "envFrom", [{"configMapRef": {"name": "x"}}]), ("probe", "httpGet", {"port": 8080}),
    ("mount", "mountPropagation", "HostToContainer"), ("spec", "updateStrategy", {"type": "OnDelete"})])
def test_a_field_the_harness_does_not_know_fails(rendered, where, field, value, tmp_path):
    documents = copy.deepcopy(rendered["dev"])
    statefulset = one(documents, "StatefulSet")
    container = statefulset["spec"]["template"]["spec"]["containers"][0]
    target = {"pod": statefulset["spec"]["template"]["spec"], "container": container, "spec": statefulset["spec"],
              "probe": container["livenessProbe"], "mount": container["volumeMounts"][0]}[where]
    target[field] = value
    with pytest.raises(harness.Unsupported, match=field):
        harness.Cluster(documents, tmp_path, "t", harness.namespace_labels())


def test_the_harness_holds_pods_to_the_namespace_pod_security_level(rendered, tmp_path):
    documents = copy.deepcopy(rendered["dev"])
    del one(documents, "Job")["spec"]["template"]["spec"]["containers"][0]["securityContext"]["capabilities"]
    with pytest.raises(harness.Unsupported, match="restricted"):
        harness.Cluster(documents, tmp_path, "t", harness.namespace_labels())


def test_yaml_files_lint_clean():
    paths = [*sorted(K8S.rglob("*.yaml")), COMPOSE]
    for path in paths:
        problems = list(linter.run(path.read_text(), LINT, str(path)))
        assert not problems, "\n".join(f"{path}:{p.line}:{p.column} {p.message}" for p in problems)


@pytest.mark.parametrize("field, where", [("readinesProbe", "container"), ("terminationGracePeriod", "pod"),
                                          ("replica", "spec")])
def test_a_misspelled_field_fails_validation(rendered, field, where):
    statefulset = copy.deepcopy(one(rendered["tls"], "StatefulSet"))
    target = {"spec": statefulset["spec"], "pod": statefulset["spec"]["template"]["spec"],
              "container": statefulset["spec"]["template"]["spec"]["containers"][0]}[where]
    target[field] = 1
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(statefulset, KUBERNETES, strict=True)


@pytest.mark.parametrize("overlay", harness.OVERLAYS)
def test_probes_ports_and_names_agree(rendered, overlay):
    documents = rendered[overlay]
    statefulset, service = one(documents, "StatefulSet"), one(documents, "Service")
    pod = statefulset["spec"]["template"]
    container = server_container(documents)
    ports = {port["name"]: port["containerPort"] for port in container["ports"]}
    config = server_config(documents)
    # The server listens where the pod says, and so does its metrics endpoint.
    assert config["server"]["address"] == f"0.0.0.0:{ports['grpc']}"
    assert config["metrics"]["address"] == f"0.0.0.0:{ports['metrics']}"
    assert pod["metadata"]["annotations"]["prometheus.io/port"] == str(ports["metrics"])
    # The probes ask grpc.health.v1 where kubelet can: the serving port in plaintext, or, with TLS,
    # the health-only listener. Readiness asks the RadServe service (a stuck worker, a drain);
    # liveness and startup the whole server.
    tls = "tls" in config
    probe_port = ports["health"] if tls else ports["grpc"]
    if tls:
        assert config["server"]["health_address"] == f"0.0.0.0:{ports['health']}"
        assert config["auth"]["tokens_file"] and config["tls"]["cert_file"] and config["tls"]["key_file"]
    else:
        assert config["server"]["insecure"] == "true" and "health" not in ports
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["grpc"]["port"] == probe_port, probe
        assert container[probe]["timeoutSeconds"] >= 3, probe  # a saturated pod answers slowly
    assert container["readinessProbe"]["grpc"]["service"] == "radserve.v1.RadServe"
    assert "service" not in container["livenessProbe"]["grpc"]
    # The startup probe waits for the catalog (~15 s) with room: a minute at least.
    startup = container["startupProbe"]
    assert startup["periodSeconds"] * startup["failureThreshold"] >= 60
    readiness = container["readinessProbe"]
    assert readiness["periodSeconds"] * readiness["failureThreshold"] >= 10
    # The Service is headless, selects the StatefulSet's pods, names the container's ports and
    # publishes the pods' names before they are ready.
    assert service["spec"]["clusterIP"] == "None" and service["spec"]["publishNotReadyAddresses"] is True
    assert statefulset["spec"]["serviceName"] == service["metadata"]["name"]
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    for port in service["spec"]["ports"]:
        assert port["targetPort"] in ports and port["port"] == ports[port["targetPort"]]
    # SIGTERM: the notice and the drain end before the kubelet's SIGKILL.
    server = config["server"]
    assert pod["spec"]["terminationGracePeriodSeconds"] > server["shutdown_notice_s"] + server["drain_timeout_s"]
    # Files the configuration names are where the Secrets are mounted.
    mounts = {mount["name"]: mount["mountPath"] for mount in container["volumeMounts"]}
    assert Path(config["replay"]["snapshot_dir"]) == Path(mounts["snapshots"])
    if tls:
        assert Path(config["auth"]["tokens_file"]).parent == Path(mounts["tokens"])
        assert Path(config["tls"]["cert_file"]).parent == Path(mounts["tls"])
    # The ConfigMap is mounted whole (a subPath mount never sees an update).
    assert not any("subPath" in mount for mount in container["volumeMounts"])
    # The learner Job names every server pod by its stable name under the headless Service.
    learner = learner_container(documents)
    assert "--address=$(RADSERVE_ADDRESSES)" in learner["args"]
    scheme = "grpcs://" if tls else ""
    pods = [f"{scheme}{statefulset['metadata']['name']}-{i}.{service['metadata']['name']}:{ports['grpc']}"
            for i in range(statefulset["spec"]["replicas"])]
    assert environment(learner)["RADSERVE_ADDRESSES"] == ",".join(pods)
    if tls:
        learner_mounts = {mount["name"]: mount["mountPath"] for mount in learner["volumeMounts"]}
        assert Path(environment(learner)["RADSERVE_TLS_CA"]).parent == Path(learner_mounts["tls"])
        (ca,) = [v for v in one(documents, "Job")["spec"]["template"]["spec"]["volumes"] if v["name"] == "tls"]
        assert ca["secret"]["items"] == [{"key": "ca.crt", "path": "ca.crt"}]  # not the servers' key


@pytest.mark.parametrize("overlay", harness.OVERLAYS)
def test_images_are_named_once(rendered, overlay):
    tag = "dev" if overlay == "dev" else VERSION
    images = {server_container(rendered[overlay])["image"], learner_container(rendered[overlay])["image"]}
    assert images == {f"radserve:{tag}", f"radserve-learner:{tag}"}


def test_a_config_change_rolls_the_servers(tree, rendered, tmp_path):
    """The ConfigMap's generated name follows its content, and the pod template follows the name."""
    changed = tmp_path / "k8s"
    shutil.copytree(tree, changed)
    config = changed / "base" / "radserve.toml"
    config.write_text(config.read_text().replace("snapshot_interval_s = 60.0", "snapshot_interval_s = 30.0"))
    before, after = rendered["tls"], harness.render(changed / "overlays" / "tls")
    names = [one(docs, "ConfigMap")["metadata"]["name"] for docs in (before, after)]
    assert names[0] != names[1] and all(name.startswith("radserve-config-") for name in names)
    for docs, name in zip((before, after), names):
        volumes = one(docs, "StatefulSet")["spec"]["template"]["spec"]["volumes"]
        assert {"name": "config", "configMap": {"name": name}} in volumes


def test_the_network_policy_admits_learners_and_scrapers(rendered, tmp_path):
    cluster = harness.Cluster(rendered["tls"], tmp_path, "t", harness.namespace_labels())
    (policy,) = cluster.policies
    server = cluster.pods[0]
    ports = {"grpc": 50051, "metrics": 9090, "health": 8081}
    learner = cluster.jobs["radserve-learner"]["pod"].labels
    scraper = {"app.kubernetes.io/name": "prometheus", "radserve/scrape": "true"}
    stranger = {"app": "something-else"}
    assert policy.admits(server, ports, 50051, learner, same_namespace=True)
    assert not policy.admits(server, ports, 9090, learner, same_namespace=True)
    assert not policy.admits(server, ports, 50051, learner, same_namespace=False)
    assert policy.admits(server, ports, 9090, scraper, same_namespace=False)
    assert not policy.admits(server, ports, 50051, scraper, same_namespace=False)
    assert not policy.admits(server, ports, 50051, stranger, same_namespace=True)
    assert not policy.admits(server, ports, 9090, stranger, same_namespace=True)
    # Not a server pod: the policy does not apply.
    assert policy.admits(cluster.jobs["radserve-learner"]["pod"], ports, 50051, stranger, same_namespace=True)
    # The budget and the spread cover the servers.
    assert cluster.budget == {"pods": ["radserve-0", "radserve-1", "radserve-2"], "max_unavailable": 1}


@pytest.mark.parametrize("overlay", harness.OVERLAYS)
def test_pods_are_locked_down(rendered, overlay):
    for kind in ("StatefulSet", "Job"):
        pod = one(rendered[overlay], kind)["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == 10001
        assert pod["securityContext"]["fsGroup"] == 10001  # the volumes are the user's to write
        for container in pod["containers"]:
            context = container["securityContext"]
            assert context == {"allowPrivilegeEscalation": False, "readOnlyRootFilesystem": True,
                               "capabilities": {"drop": ["ALL"]}}, (kind, context)
            limits = container["resources"]["limits"]
            assert "memory" in limits, kind
    volumes = {volume["name"]: volume for volume in one(rendered[overlay], "StatefulSet")["spec"]["template"]["spec"]["volumes"]}
    assert volumes["dshm"]["emptyDir"]["medium"] == "Memory"
    runs = {v["name"]: v for v in one(rendered[overlay], "Job")["spec"]["template"]["spec"]["volumes"]}["runs"]
    assert runs["persistentVolumeClaim"]["claimName"] == "radserve-runs"


def test_the_config_map_is_a_config_the_server_accepts(rendered, tmp_path):
    """The ConfigMap's radserve.toml starts the real server (where the cluster's paths and addresses
    are swapped for local ones by the server's own RADSERVE__ variables)."""
    config = tmp_path / "radserve.toml"
    config.write_text(one(rendered["tls"], "ConfigMap")["data"]["radserve.toml"])
    tokens = tmp_path / "tokens.toml"
    tokens.write_text('[[principal]]\nname = "learner"\nrole = "user"\ntoken_sha256 = ["' + "0" * 64 + '"]\n')
    server = radserve.LocalServer(env={"RADSERVE__SERVER__ADDRESS": "127.0.0.1:0",
                                       "RADSERVE__METRICS__ADDRESS": "127.0.0.1:0",
                                       "RADSERVE__AUTH__TOKENS_FILE": str(tokens),
                                       "RADSERVE__REPLAY__SNAPSHOT_DIR": str(tmp_path / "snapshots"),
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
