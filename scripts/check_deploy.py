#!/usr/bin/env python3
"""Checks the deploy files of a checkout (default: this one) for what their documentation says
they must do; exits 1 with one line per failure.

- Every Kubernetes manifest validates, strictly, against the Kubernetes API schema
  (kubernetes-validate, from PyPI; setup.sh --test installs it).
- Kustomizations name files that exist, images with a registry and a tag other than latest,
  and replica counts of workloads that exist.
- A StatefulSet's serviceName is a headless Service; relfusiond's pods run as non-root and
  carry Prometheus scrape annotations.
- compose: every service restarts by itself; relfusiond has a healthcheck.
- The image: a --locked build, a non-root USER, the libraries and ICD file NVIDIA's Vulkan
  driver needs; .dockerignore keeps target/ out of the build context.
"""
import pathlib
import subprocess
import sys

import yaml

failures = []


def fail(msg):
    failures.append(msg)


def docs(path):
    with open(path) as f:
        return [d for d in yaml.safe_load_all(f) if d]


def check_k8s(k8s):
    manifests = [p for p in sorted(k8s.rglob("*.yaml")) if p.name != "kustomization.yaml"]
    result = subprocess.run(
        [sys.executable, "-m", "kubernetes_validate", "--strict", "--quiet", *map(str, manifests)],
        capture_output=True,
        text=True,
    )
    if result.returncode != 0:
        fail(f"kubernetes-validate: {result.stdout.strip()} {result.stderr.strip()}")
    resources = [d for p in manifests for d in docs(p)]
    by_kind = {}
    for d in resources:
        by_kind.setdefault(d["kind"], {})[d["metadata"]["name"]] = d
    services = by_kind.get("Service", {})
    for name, sts in by_kind.get("StatefulSet", {}).items():
        svc = services.get(sts["spec"].get("serviceName"))
        if svc is None or svc["spec"].get("clusterIP") != "None":
            fail(f"StatefulSet {name}: serviceName {sts['spec'].get('serviceName')!r} is not a headless Service")
    relfusiond = by_kind.get("StatefulSet", {}).get("relfusiond")
    if relfusiond is None:
        fail("no StatefulSet relfusiond")
    else:
        pod = relfusiond["spec"]["template"]
        if not pod["spec"].get("securityContext", {}).get("runAsNonRoot"):
            fail("relfusiond pods may run as root (securityContext.runAsNonRoot)")
        notes = pod["metadata"].get("annotations", {})
        if notes.get("prometheus.io/scrape") != "true" or notes.get("prometheus.io/path") != "/metrics":
            fail("relfusiond pods lack the Prometheus scrape annotations")
    workloads = set(by_kind.get("StatefulSet", {})) | set(by_kind.get("Deployment", {}))
    for kust in sorted(k8s.rglob("kustomization.yaml")):
        k = docs(kust)[0]
        base = kust.parent
        for res in k.get("resources", []):
            if not (base / res).exists():
                fail(f"{kust}: resource {res} does not exist")
        for gen in k.get("configMapGenerator", []):
            for f in gen.get("files", []):
                if not (base / f.split("=")[-1]).exists():
                    fail(f"{kust}: configMap file {f} does not exist")
        for img in k.get("images", []):
            name, tag = img.get("newName", img["name"]), str(img.get("newTag", "latest"))
            if "/" not in name or "." not in name.split("/")[0] or tag == "latest":
                fail(f"{kust}: image {name}:{tag} has no registry or is :latest")
        for rep in k.get("replicas", []):
            if rep["name"] not in workloads:
                fail(f"{kust}: replicas of unknown workload {rep['name']}")
    for d in resources:
        for c in d.get("spec", {}).get("template", {}).get("spec", {}).get("containers", []) + \
                d.get("spec", {}).get("template", {}).get("spec", {}).get("initContainers", []):
            if c["image"].endswith(":latest"):
                fail(f"{d['kind']} {d['metadata']['name']}: image {c['image']} is :latest")


def check_compose(path):
    compose = docs(path)[0]
    # A one-shot service (another waits for it to complete) needs no restart policy.
    oneshots = {
        dep_name
        for other in compose["services"].values()
        if isinstance(other.get("depends_on"), dict)
        for dep_name, dep in other["depends_on"].items()
        if dep.get("condition") == "service_completed_successfully"
    }
    for name, svc in compose["services"].items():
        if name not in oneshots and svc.get("restart") not in ("always", "unless-stopped", "on-failure"):
            fail(f"compose: service {name} has no restart policy")
    if "healthcheck" not in compose["services"].get("relfusiond", {}):
        fail("compose: relfusiond has no healthcheck")


def check_image(root):
    dockerfile = (root / "deploy" / "Dockerfile").read_text()
    for needle, why in [
        ("--locked", "the build is not --locked"),
        ("\nUSER ", "the container runs as root (no USER)"),
        ("libglvnd0", "NVIDIA's Vulkan driver needs libglvnd0"),
        ("libxext6", "NVIDIA's Vulkan driver needs libxext6"),
        ("/etc/vulkan/icd.d/nvidia_icd.json", "no NVIDIA Vulkan ICD file"),
        ("HEALTHCHECK", "no HEALTHCHECK"),
        ("ARG ORT_PACKAGE=onnxruntime", "no build argument for the GPU build of ONNX Runtime"),
        ('"${ORT_PACKAGE}==', "the ONNX Runtime package does not follow ORT_PACKAGE"),
    ]:
        if needle not in dockerfile:
            fail(f"Dockerfile: {why}")
    ignore = root / ".dockerignore"
    if not ignore.exists() or "target/" not in ignore.read_text().split():
        fail(".dockerignore does not keep target/ out of the build context")


def main():
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else pathlib.Path(__file__).parent.parent)
    check_k8s(root / "deploy" / "k8s")
    check_compose(root / "deploy" / "compose.yaml")
    check_image(root)
    for f in failures:
        print(f)
    sys.exit(1 if failures else 0)


main()
