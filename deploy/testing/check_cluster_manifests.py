#!/usr/bin/python3
"""Checks deploy/k8s/cluster and deploy/compose-cluster.yaml without kubectl or docker (issue 18):
every file parses (python3-yaml), kustomization resources exist, each workload's selector matches
its pod labels and a Service / PodDisruptionBudget / HorizontalPodAutoscaler selects or targets
an existing workload, headless Services for NATS, etcd and shards, the placedb-server flags are
the agreed cluster flags, no image names a registry host, and the NATS configs fsync every write.
Internal TLS is on everywhere (issue 35): placedb shards and workers set PLACEDB_INTERNAL_TLS, every
NATS config has `tls { ... verify: true }` for clients and for routes, and every etcd member serves
https with --client-cert-auth and --peer-client-cert-auth, naming the same certificate files.

  /usr/bin/python3 deploy/testing/check_cluster_manifests.py     # exit 0: OK
"""

import os
import re
import sys

import yaml

DEPLOY = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
K8S = os.path.join(DEPLOY, "k8s", "cluster")
FLAGS = {"--role", "--cluster-name", "--nats", "--etcd", "--shard-id", "--advertise",
         "--internal-listen"}
errors = []


def check(ok, message):
    if not ok:
        errors.append(message)


def registry_free(image, where):
    # A registry host has a dot or a colon (port) before the first slash, or is "localhost".
    first = image.split("/")[0] if "/" in image else ""
    check(not ("." in first or ":" in first or first == "localhost"),
          f"{where}: image {image} names a registry host")


def placedb_flags(args, where):
    for arg in args:
        if arg.startswith("--") and arg.split("=")[0] in FLAGS | {"--role"}:
            continue
        check(not arg.startswith("--") or arg.split("=")[0] not in {"--cluster", "--shard"},
              f"{where}: unknown cluster flag {arg}")
    names = {a.split("=")[0] for a in args if a.startswith("--")}
    check("--role" in names, f"{where}: no --role")
    check(names <= FLAGS, f"{where}: flags {sorted(names - FLAGS)} are not the agreed ones")


TRUE = {"on", "true", "1", "yes"}
ETCD_TLS = {"--cert-file", "--key-file", "--trusted-ca-file", "--client-cert-auth",
            "--peer-cert-file", "--peer-key-file", "--peer-trusted-ca-file",
            "--peer-client-cert-auth"}


def nats_tls(conf, where):
    # Client TLS before `cluster {`, route TLS inside it; each with a CA and verify: true.
    top, _, cluster = conf.partition("cluster {")
    for part, what in ((top, "clients"), (cluster, "routes")):
        block = re.search(r"tls\s*\{([^}]*)\}", part)
        check(block and all(k in block.group(1) for k in ("cert_file", "key_file", "ca_file")) and
              re.search(r"verify:\s*true", block.group(1)),
              f"{where}: no TLS with verify: true for {what}")


def etcd_tls(args, where):
    names = {a.split("=")[0] for a in args}
    check(ETCD_TLS <= names, f"{where}: etcd without {sorted(ETCD_TLS - names)}")
    for a in args:
        if a.split("=")[0] in ("--listen-client-urls", "--advertise-client-urls",
                               "--listen-peer-urls", "--initial-advertise-peer-urls",
                               "--initial-cluster"):
            check("http://" not in a, f"{where}: {a.split('=')[0]} is plain http")


def internal_tls(env, where):
    check(str(env.get("PLACEDB_INTERNAL_TLS", "")).lower() in TRUE,
          f"{where}: PLACEDB_INTERNAL_TLS is not on")
    check(all(env.get(k) for k in ("PLACEDB_TLS_CERT_FILE", "PLACEDB_TLS_KEY_FILE")) and
          (env.get("PLACEDB_INTERNAL_CA_FILE") or env.get("PLACEDB_TLS_CLIENT_CA_FILE")),
          f"{where}: internal TLS without its certificate, key or CA file")


kustomization = yaml.safe_load(open(os.path.join(K8S, "kustomization.yaml")))
docs = []
for resource in kustomization["resources"]:
    path = os.path.join(K8S, resource)
    check(os.path.exists(path), f"kustomization: {resource} missing")
    docs += [(resource, d) for d in yaml.safe_load_all(open(path)) if d]
workloads = {(d["kind"], d["metadata"]["name"]): d for _, d in docs
             if d["kind"] in ("StatefulSet", "Deployment")}
pod_labels = [w["spec"]["template"]["metadata"]["labels"] for w in workloads.values()]


def selects(selector):
    return any(all(labels.get(k) == v for k, v in selector.items()) for labels in pod_labels)


for (kind, name), w in workloads.items():
    spec = w["spec"]
    labels = spec["template"]["metadata"]["labels"]
    check(all(labels.get(k) == v for k, v in spec["selector"]["matchLabels"].items()),
          f"{kind}/{name}: selector does not match its pod labels")
    if kind == "StatefulSet":
        check(any(d["kind"] == "Service" and d["metadata"]["name"] == spec["serviceName"] and
                  d["spec"].get("clusterIP") == "None" for _, d in docs),
              f"{kind}/{name}: governing Service {spec['serviceName']} missing or not headless")
        check("volumeClaimTemplates" in spec, f"{kind}/{name}: no PVC")
    for c in spec["template"]["spec"]["containers"]:
        registry_free(c["image"], f"{kind}/{name}")
        if c["image"].startswith("placedb"):
            placedb_flags(c.get("args", []), f"{kind}/{name}")
            internal_tls({e["name"]: e.get("value") for e in c.get("env", [])}, f"{kind}/{name}")
        if c["image"].startswith("bitnami/etcd"):
            etcd_tls(c.get("command", []) + c.get("args", []), f"{kind}/{name}")
for file, d in docs:
    kind, name = d["kind"], d["metadata"]["name"]
    if kind == "Service":
        check(selects(d["spec"]["selector"]), f"Service/{name} selects no workload")
    if kind == "PodDisruptionBudget":
        check(selects(d["spec"]["selector"]["matchLabels"]), f"PDB/{name} selects no workload")
    if kind == "HorizontalPodAutoscaler":
        target = d["spec"]["scaleTargetRef"]
        check((target["kind"], target["name"]) in workloads, f"HPA/{name}: no target")
        check(any(m["resource"]["name"] == "cpu" for m in d["spec"]["metrics"]), f"HPA/{name}: not CPU")
    if kind == "ConfigMap" and "nats.conf" in d.get("data", {}):
        check(re.search(r"sync_interval:\s*always", d["data"]["nats.conf"]),
              f"ConfigMap/{name}: nats without sync_interval always")
        nats_tls(d["data"]["nats.conf"], f"ConfigMap/{name}")
kinds = {(d["kind"], d["metadata"]["name"]) for _, d in docs}
for needed in [("StatefulSet", "placedb-nats"), ("StatefulSet", "placedb-etcd"),
               ("StatefulSet", "placedb-shard"), ("Deployment", "placedb-worker"),
               ("HorizontalPodAutoscaler", "placedb-worker")]:
    check(needed in kinds, f"missing {needed[0]}/{needed[1]}")
for name in ("placedb-nats", "placedb-etcd", "placedb-shard", "placedb-worker"):
    check(("PodDisruptionBudget", name) in kinds, f"missing PodDisruptionBudget/{name}")
check(all(w["spec"]["replicas"] == 3 for (k, n), w in workloads.items()
          if n in ("placedb-nats", "placedb-etcd")), "NATS and etcd: 3 replicas each")

compose = yaml.safe_load(open(os.path.join(DEPLOY, "compose-cluster.yaml")))
services = compose["services"]
for i in (1, 2, 3):
    for role in ("nats", "etcd", "shard", "worker"):
        check(f"{role}-{i}" in services, f"compose: {role}-{i} missing")
for name, s in services.items():
    registry_free(s["image"].split("${PLACEDB_IMAGE:-")[-1].rstrip("}"), f"compose {name}")
    if name.startswith(("shard-", "worker-")):
        placedb_flags(s["command"], f"compose {name}")
        internal_tls(s["environment"], f"compose {name}")
    if name.startswith("etcd-"):
        etcd_tls(s["command"], f"compose {name}")
    for v in s.get("volumes", []):
        check(v.split(":")[0] in compose["volumes"], f"compose {name}: volume {v} not declared")
for name, c in compose["configs"].items():
    check(re.search(r"sync_interval:\s*always", c["content"]), f"compose config {name}: no fsync")
    nats_tls(c["content"], f"compose config {name}")

for e in errors:
    print("check_cluster_manifests:", e, file=sys.stderr)
print(f"check_cluster_manifests: {len(docs)} k8s objects, {len(services)} compose services: "
      + ("OK" if not errors else f"{len(errors)} error(s)"))
sys.exit(1 if errors else 0)
