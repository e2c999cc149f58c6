"""The Kubernetes overlays run as written, under Docker (`make test-cluster`): each overlay rendered
by kustomize, every pod of its StatefulSet and its learner Job started the way its spec says
(tests/k8s_harness.py), kubelet's probes run against the servers with their own ports, timings and
thresholds, and the learner Job started at the same moment as the servers, so that it must wait for
them, running to its end (the short run of components/short-run, as the runbook's first run).

The tls overlays run with TLS and tokens on: the probes pass on the plaintext health listener, the
learner reaches the servers over TLS, checking their certificates against the CA it was given. The
cert-manager objects of overlays/tls are issued as cert-manager issues them (the harness); the tokens
are made with the image (`docker run --rm IMAGE token`), as the runbook says.
"""

import os
import time
import uuid

import kubernetes_validate
import pytest

import k8s_harness as harness  # tests/ is on sys.path: tests/cluster is a package of tests/ (pytest's rootdir)

TAG = os.environ.get("RADSERVE_TAG", "dev")
JOB_LIMIT_S = 1200
LATE_S = 20


def images_for(cluster: harness.Cluster) -> None:
    """The images the overlay names, as loaded into a cluster: the ones built here under its tag."""
    wanted = {pod.image for pod in cluster.pods} | {job["pod"].image for job in cluster.jobs.values()}
    for image in wanted:
        repository = image.rsplit(":", 1)[0]
        built = f"{repository}:{TAG}"
        if not harness.docker("image", "ls", "-q", built):
            pytest.fail(f"no image {built}: make test-cluster builds it (docker/build.sh --with-torch)")
        if image != built:
            harness.docker("tag", built, image)


@pytest.mark.parametrize("overlay", ["dev", "tls", "tls-secret"])
def test_an_overlay_runs_as_written(overlay, tmp_path):
    tree = harness.prepare(tmp_path, ["docker", "run", "--rm", f"radserve:{TAG}", "token"])
    # dev has the short run already; the others get it as the runbook's first run does.
    documents = harness.overlay_documents(tree, overlay, short_run=overlay != "dev")
    for document in documents:
        if document["kind"] not in ("Certificate", "Issuer"):  # cert-manager's: read field by field below
            kubernetes_validate.validate(document, kubernetes_validate.latest_version(), strict=True)
    cluster = harness.Cluster(documents, tmp_path / "cluster", f"radserve-k8s-{uuid.uuid4().hex[:8]}",
                              harness.namespace_labels())
    images_for(cluster)
    with harness.Running(cluster) as running:
        # `kubectl apply -k` starts everything at once, and the learner waits for the servers. In the
        # tls overlay it starts LATE_S before them, as when the servers' images are still being
        # pulled: their names do not resolve yet, then they answer NOT_SERVING, then SERVING.
        running.start_job("radserve-learner")
        if overlay == "tls":
            time.sleep(LATE_S)
        for pod in cluster.pods:
            running.start(pod)
        succeeded, log = running.wait_job("radserve-learner", JOB_LIMIT_S)
        server_logs = "\n".join(f"--- {pod.name}\n{running.logs(pod)}" for pod in cluster.pods)
        assert succeeded, f"the learner Job failed:\n{log}\n{server_logs}"
        print(f"\n{overlay}: learner finished; its last lines:\n" + "\n".join(log.strip().splitlines()[-2:]))
        # TLS is on where the overlay says: the serving port refuses plaintext, and the probes pass
        # on the health listener all the same.
        for pod in cluster.pods:
            address = running.probers[pod.name].address
            assert harness.grpc_health(f"{address}:50051", "", 5) == (overlay == "dev"), pod.name
        for pod in cluster.pods:
            prober = running.probers[pod.name]
            assert prober.started_after is not None, f"{pod.name} never passed its startup probe\n{server_logs}"
            assert not prober.failed, f"{pod.name}: {prober.failed}\n{server_logs}"
            assert prober.ready, f"{pod.name} not ready at the end: {prober.readiness_changes}\n{server_logs}"
            drops = [when for when, ready in prober.readiness_changes if not ready]
            assert not drops, f"{pod.name} left readiness at {drops} s while the learner ran"
            slowest = {kind: max(times) for kind, times in prober.latencies.items() if times}
            print(f"{pod.name}: started after {prober.started_after:.0f} s; slowest probe answers (s): "
                  + ", ".join(f"{kind} {seconds:.2f}" for kind, seconds in slowest.items()))
        # The run went to the claim, as the Job's volume says.
        runs = tmp_path / "cluster" / "claims" / "radserve-runs"
        summaries = list(runs.glob("*/summary.txt"))
        assert summaries, f"no run in the radserve-runs claim: {sorted(p.name for p in runs.iterdir())}"
        print(f"run: {summaries[0].read_text().strip()}")
