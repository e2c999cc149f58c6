"""Authentication, TLS and ownership end to end: the real server with a tokens file and certificates
made here (trustme), the Python client as users use it. The per-RPC table (every method without a
token, with another principal's session) is server/radserve/tests/security.rs."""

import subprocess

import grpc
import numpy as np
import pytest
import trustme
from grpc_health.v1 import health_pb2, health_pb2_grpc

import radserve
from _procs import wait_serving
from radserve.server import find_binary


def _free_port() -> int:
    import socket
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def new_token(name: str, role: str = "user") -> "tuple[str, str]":
    """`radserve token`: the token (stdout) and its tokens-file entry (stderr)."""
    made = subprocess.run([find_binary(), "token", "--name", name, "--role", role], capture_output=True, text=True,
                          check=True)
    entry = "\n".join(line for line in made.stderr.splitlines() if not line.startswith("#"))
    return made.stdout.strip(), entry


@pytest.fixture(scope="module")
def ca():
    return trustme.CA()


@pytest.fixture(scope="module")
def secured(tmp_path_factory, ca):
    """A server with tokens for alice (at most 2 sessions), bob, ops (admin) and grafana (monitor),
    and TLS."""
    folder = tmp_path_factory.mktemp("security")
    tokens, entries = {}, []
    for name, role in (("alice", "user"), ("bob", "user"), ("ops", "admin"), ("grafana", "monitor")):
        tokens[name], entry = new_token(name, role)
        entries.append(entry + ("\nmax_sessions = 2" if name == "alice" else ""))
    (folder / "tokens.toml").write_text("\n\n".join(entries) + "\n")
    certificate = ca.issue_cert("localhost", "127.0.0.1")
    certificate.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    certificate.private_key_pem.write_to_path(str(folder / "key.pem"))
    ca.cert_pem.write_to_path(str(folder / "ca.pem"))
    env = {
        "RADSERVE__AUTH__TOKENS_FILE": str(folder / "tokens.toml"),
        "RADSERVE__TLS__CERT_FILE": str(folder / "cert.pem"),
        "RADSERVE__TLS__KEY_FILE": str(folder / "key.pem"),
    }
    with radserve.LocalServer(workers=1, env=env) as server:
        port = server.address.rsplit(":", 1)[1]
        yield {"address": f"grpcs://localhost:{port}", "tokens": tokens, "ca": folder / "ca.pem", "folder": folder}


def connect(secured, name: "str | None", **kwargs) -> radserve.Client:
    token = secured["tokens"][name] if name else None
    return radserve.Client(secured["address"], token=token, tls=radserve.TlsConfig(ca=secured["ca"]), **kwargs)


def test_calls_without_a_known_token_are_refused_and_health_stays_open(secured, monkeypatch):
    monkeypatch.delenv("RADSERVE_TOKEN", raising=False)
    with connect(secured, None) as anonymous:
        with pytest.raises(radserve.UnauthenticatedError, match="bearer token"):
            anonymous.list_envs()
    with radserve.Client(secured["address"], token="radserve_" + "0" * 64, tls=radserve.TlsConfig(ca=secured["ca"])) as wrong:
        with pytest.raises(radserve.UnauthenticatedError, match="not one this server accepts"):
            wrong.list_sessions()
    # Probes carry no token (SERVING once the catalog is built).
    credentials = grpc.ssl_channel_credentials(root_certificates=secured["ca"].read_bytes())
    with grpc.secure_channel(secured["address"].removeprefix("grpcs://"), credentials) as channel:
        wait_serving(channel)
    # The token from the environment, as a job gets it from a Secret.
    monkeypatch.setenv("RADSERVE_TOKEN", secured["tokens"]["bob"])
    with connect(secured, None) as from_environment:
        assert from_environment.list_sessions() == []


def test_tls_is_required_and_checked(secured):
    port = secured["address"].rsplit(":", 1)[1]
    # Plain gRPC to a TLS port: the handshake never completes.
    with pytest.raises(radserve.UnavailableError):
        radserve.Client(f"127.0.0.1:{port}", token=secured["tokens"]["bob"], wait_ready=2)
    # A server certificate from a CA the client does not trust.
    other = secured["folder"] / "other-ca.pem"
    trustme.CA().cert_pem.write_to_path(str(other))
    with pytest.raises(radserve.UnavailableError):
        radserve.Client(secured["address"], token=secured["tokens"]["bob"], tls=radserve.TlsConfig(ca=other), wait_ready=2)


def test_tls_files_from_the_environment(secured, monkeypatch):
    """A grpcs:// address with no TlsConfig takes its CA from RADSERVE_TLS_CA (as a Kubernetes Job
    gets it, a mounted Secret); without it, the system's CAs do not know the test CA."""
    monkeypatch.setenv("RADSERVE_TOKEN", secured["tokens"]["bob"])
    monkeypatch.delenv("RADSERVE_TLS_CA", raising=False)
    with pytest.raises(radserve.UnavailableError):
        radserve.Client(secured["address"], wait_ready=2)
    monkeypatch.setenv("RADSERVE_TLS_CA", str(secured["ca"]))
    assert radserve.TlsConfig.from_environment() == radserve.TlsConfig(ca=str(secured["ca"]))
    with radserve.Client(secured["address"], wait_ready_s=30) as client:
        assert client.list_sessions() == []
    # A name to check the certificate against, other than the address's host.
    port = secured["address"].rsplit(":", 1)[1]
    monkeypatch.setenv("RADSERVE_TLS_SERVER_NAME", "localhost")
    with radserve.Client(f"grpcs://127.0.0.1:{port}", wait_ready=10) as by_ip:
        assert by_ip.list_sessions() == []
    monkeypatch.setenv("RADSERVE_TLS_SERVER_NAME", "radserve-9.elsewhere")
    with pytest.raises(radserve.UnavailableError):
        radserve.Client(f"grpcs://127.0.0.1:{port}", wait_ready=2)


def test_sessions_belong_to_their_creator(secured):
    with connect(secured, "alice") as alice, connect(secured, "bob") as bob, \
            connect(secured, "ops") as ops, connect(secured, "grafana") as grafana:
        envs = alice.make_vec("gym/CartPole-v1", num_envs=2, seed=1)
        try:
            envs.reset()
            session = envs.session_id
            # To bob, alice's session and one never created are the same: unknown.
            for session_id in (session, session[:-4] + "0000"):
                for call in (lambda: bob.describe_session(session_id), lambda: bob.close_session(session_id),
                             lambda: bob.sample_batches(session_id, 2)):
                    with pytest.raises(radserve.NotFoundError, match="unknown session"):
                        call()
            assert bob.list_sessions() == []
            # A monitor sees every session and its owner, and changes nothing.
            listed = grafana.list_sessions()
            assert [(s.session_id, s.owner) for s in listed] == [(session, "alice")]
            assert grafana.describe_session(session).num_envs == 2
            with pytest.raises(radserve.PermissionDeniedError, match="monitor"):
                grafana.make_vec("gym/CartPole-v1", num_envs=1)
            # Alice's own limit: two sessions.
            second = alice.make_vec("gym/CartPole-v1", num_envs=1)
            with pytest.raises(radserve.ResourceExhaustedError, match="principal 'alice'.*max_sessions"):
                alice.make_vec("gym/CartPole-v1", num_envs=1)
            second.close()
            # The owner acts through shared memory as through gRPC, over TLS with its token.
            shared = alice.make_vec("gym/CartPole-v1", num_envs=2, seed=1, delivery="shared_memory")
            assert shared.delivery == "shared_memory"
            shared.reset(seed=1)
            assert shared.step(np.zeros(2, np.int64))[0].shape == (2, 4)
            shared.close()
            # An admin sees and closes anyone's session; alice then learns it is gone.
            assert [s.owner for s in ops.list_sessions()] == ["alice"]
            ops.close_session(session)
            with pytest.raises(radserve.NotFoundError):
                envs.step(np.zeros(2, np.int64))
        finally:
            envs.close()


def test_mutual_tls_admits_only_clients_the_ca_signed(tmp_path, ca):
    certificate = ca.issue_cert("localhost")
    certificate.cert_chain_pems[0].write_to_path(str(tmp_path / "cert.pem"))
    certificate.private_key_pem.write_to_path(str(tmp_path / "key.pem"))
    ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    client_ca = trustme.CA()
    client_ca.cert_pem.write_to_path(str(tmp_path / "client-ca.pem"))
    env = {
        "RADSERVE__TLS__CERT_FILE": str(tmp_path / "cert.pem"),
        "RADSERVE__TLS__KEY_FILE": str(tmp_path / "key.pem"),
        "RADSERVE__TLS__CLIENT_CA_FILE": str(tmp_path / "client-ca.pem"),
    }

    def client_cert(issuer, name):
        issued = issuer.issue_cert(f"{name}.example")
        issued.cert_chain_pems[0].write_to_path(str(tmp_path / f"{name}.pem"))
        issued.private_key_pem.write_to_path(str(tmp_path / f"{name}.key"))
        return radserve.TlsConfig(ca=tmp_path / "ca.pem", cert=tmp_path / f"{name}.pem", key=tmp_path / f"{name}.key")

    health_port = _free_port()
    env["RADSERVE__SERVER__HEALTH_ADDRESS"] = f"127.0.0.1:{health_port}"
    with radserve.LocalServer(workers=1, env=env) as server:
        address = "grpcs://localhost:" + server.address.rsplit(":", 1)[1]
        with radserve.Client(address, tls=client_cert(client_ca, "learner"), wait_ready_s=120) as admitted:
            assert any(env.id == "gym/CartPole-v1" for env in admitted.list_envs("gym/"))
        for refused in (radserve.TlsConfig(ca=tmp_path / "ca.pem"), client_cert(trustme.CA(), "stranger")):
            with pytest.raises(radserve.RadServeError):
                with radserve.Client(address, tls=refused, wait_ready=3) as client:
                    client.list_sessions()

        # `radserve healthcheck` presents a client certificate to a mutual-TLS server (an exec probe).
        def healthcheck(*args):
            return subprocess.run([find_binary(), "healthcheck", "--address", server.address, "--ca",
                                   str(tmp_path / "ca.pem"), "--server-name", "localhost", *args],
                                  capture_output=True, text=True, timeout=60)
        checked = healthcheck("--cert", str(tmp_path / "learner.pem"), "--key", str(tmp_path / "learner.key"))
        assert checked.returncode == 0 and checked.stdout.strip() == "SERVING", checked.stderr
        assert healthcheck().returncode != 0, "without a certificate the server refuses the probe"

        # The health-only listener: kubelet's gRPC probe in plaintext, no certificate, no token;
        # it serves grpc.health.v1 and nothing else.
        with grpc.insecure_channel(f"127.0.0.1:{health_port}") as channel:
            probe = health_pb2_grpc.HealthStub(channel)
            assert probe.Check(health_pb2.HealthCheckRequest(), timeout=10).status == health_pb2.HealthCheckResponse.SERVING
            service = health_pb2.HealthCheckRequest(service="radserve.v1.RadServe")
            assert probe.Check(service, timeout=10).status == health_pb2.HealthCheckResponse.SERVING
            from radserve._proto import radserve_pb2, radserve_pb2_grpc
            with pytest.raises(grpc.RpcError) as refused_call:
                radserve_pb2_grpc.RadServeStub(channel).ListSessions(radserve_pb2.ListSessionsRequest(), timeout=10)
            assert refused_call.value.code() == grpc.StatusCode.UNIMPLEMENTED


def test_an_open_server_on_a_reachable_address_is_refused_unless_insecure():
    refused = subprocess.run([find_binary(), "serve", "--address", "0.0.0.0:0", "--workers", "1"],
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0
    assert "refusing to serve 0.0.0.0" in refused.stderr and "--insecure" in refused.stderr
    # Opted in: it serves.
    server = radserve.LocalServer(workers=1, address="0.0.0.0:0")
    server.args.append("--insecure")
    with server, radserve.Client("127.0.0.1:" + server.address.rsplit(":", 1)[1]) as client:
        assert client.list_sessions() == []


def test_the_token_helper_prints_a_fresh_token_and_its_entry():
    first, entry = new_token("carol", "admin")
    second, _ = new_token("carol")
    assert first != second and first.startswith("radserve_") and len(first) == 73
    assert 'name = "carol"' in entry and 'role = "admin"' in entry and first not in entry
    bad = subprocess.run([find_binary(), "token", "--name", "x", "--role", "root"], capture_output=True, text=True)
    assert bad.returncode != 0 and "user, monitor or admin" in bad.stderr
