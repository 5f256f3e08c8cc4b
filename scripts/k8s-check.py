#!/usr/bin/env python3
"""Checks deploy/k8s/twinswarm-shards.yaml as far as this machine allows (no cluster, no
container daemon, loopback only; docs/sharding.md, "A dead machine").

  static  (under 1 s) kubectl's own decoder, offline, then the objects' structure: the
          StatefulSet's replicas against the N its scripts hard-code, volume mounts against
          volumes, the Service against the pods' labels, the ports and DNS names the routers
          use, the log epoch, the image and its pull policy, fields the Kubernetes API lacks.
  smoke   (about 30 s on 2 cores; 15 s with --no-logs) static, what can be said of the image
          without building it, then the pods' container scripts, expanded as the kubelet
          expands them ($(VAR) from the container's env, $$ -> $), run for real on loopback
          for every pod (a router and a shard per pod, restartPolicy Always), every copter's
          final digest compared with an uninterrupted one-process run's, the shards' logs
          merged and compared with the one-process log. No fault. For CI.
  full    (about 70 s; 130 s when a router keeps a dead shard's token, see the docs) static,
          then the same pods with a dead machine: once every shard has a checkpoint, one pod's
          router and shard are SIGKILLed (--fault freeze: SIGSTOPped, a machine that stops
          answering); its neighbours must stop on their own ("shard K left the cluster"), the
          pod comes back --dead-s later, every shard container restarts (as the kubelet does)
          and resumes from the newest tick all N shards have a checkpoint for; the run must
          end with the one-process digests, and stay ended. The killed pod's torn logs are
          recovered (`log recover`) and all logs merged (`log merge`) and compared. Then again
          with the pod back after --quick-restart-s (a crashed container restarted at once).

The only changes to what the manifest runs are listed in the report (each one is counted in
the script text it changes): loopback ports for the pods' addresses and DNS names, temporary
directories for the volumes, HOSTNAME per pod, `twinswarm` first on PATH, and `--json` on the
shard's `twinswarm run` (its per-copter digests; the text summary has none).

  scripts/k8s-check.py [--mode static|smoke|full] [--bin PATH] [--keep] [--no-logs]
Python 3, standard library only; the log comparison needs PyPI `mcap` and
`mcap-protobuf-support` (the repository's .venv has them; without them it is skipped).
Exit status 0 when every check passed, 1 otherwise (warnings do not fail).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = ROOT / "deploy/k8s/twinswarm-shards.yaml"


# ----------------------------------------------------------------------------- reporting
class Report:
    def __init__(self):
        self.fails: list[str] = []
        self.warns: list[str] = []
        self.t0 = time.monotonic()

    def _p(self, tag, msg):
        print(f"[{time.monotonic() - self.t0:6.1f}s] {tag:4} {msg}", flush=True)

    def ok(self, msg):
        self._p("ok", msg)

    def fail(self, msg):
        self.fails.append(msg)
        self._p("FAIL", msg)

    def warn(self, msg):
        self.warns.append(msg)
        self._p("warn", msg)

    def info(self, msg):
        self._p("", msg)

    def check(self, cond, msg, detail=""):
        if cond:
            self.ok(msg)
        else:
            self.fail(msg + (f": {detail}" if detail else ""))
        return cond

    def section(self, title):
        print(f"\n== {title}", flush=True)


# ----------------------------------------------------------------------------- step 1
def kubectl_decode(manifest: Path, work: Path, rep: Report) -> list[dict]:
    """The manifest's objects as kubectl decodes them, offline.

    `kubectl create --dry-run=client` needs the API server's discovery (REST mapping) even with
    --validate=false, so it cannot run here; `kubectl label --local` decodes the same files with
    the same decoder and needs no server. A kubeconfig pointing at a closed loopback port makes
    sure nothing is asked of a server (it would fail with "connection refused")."""
    kubeconfig = work / "kubeconfig"
    kubeconfig.write_text(
        "apiVersion: v1\nkind: Config\nclusters:\n- name: none\n  cluster: {server: 'http://127.0.0.1:9'}\n"
        "users:\n- name: none\n  user: {token: none}\n"
        "contexts:\n- name: none\n  context: {cluster: none, user: none}\ncurrent-context: none\n")
    env = dict(os.environ, KUBECONFIG=str(kubeconfig))
    if not shutil.which("kubectl"):
        rep.fail("kubectl not found")
        return []
    version = subprocess.run(["kubectl", "version", "--client"], capture_output=True, text=True, env=env).stdout
    rep.info("kubectl: " + " / ".join(version.split("\n")[:1]))
    create = subprocess.run(["kubectl", "create", "--dry-run=client", "--validate=false", "-o", "json", "-f",
                             str(manifest)], capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
    if create.returncode == 0:
        rep.ok("kubectl create --dry-run=client --validate=false decodes the manifest offline")
        text = create.stdout
    else:
        first = next((l for l in create.stderr.splitlines() if "unable to recognize" in l), create.stderr[:200])
        rep.info("kubectl create --dry-run=client needs the API server's discovery even offline "
                 f"({first.strip()}); decoding with `kubectl label --local -o json` instead (no server)")
        label = subprocess.run(["kubectl", "label", "--local", "-o", "json", "-f", str(manifest), "k8s-check-"],
                               capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
        if label.returncode != 0:
            rep.fail(f"kubectl label --local cannot decode the manifest: {label.stderr.strip()}")
            return []
        text = label.stdout
    objs, dec, i = [], json.JSONDecoder(), 0
    while True:
        while i < len(text) and text[i].isspace():
            i += 1
        if i >= len(text):
            break
        o, i = dec.raw_decode(text, i)
        objs.extend(o["items"] if o.get("kind") == "List" else [o])
    for o in objs:  # `label --local` adds an empty labels map; it was not in the file
        if o.get("metadata", {}).get("labels") == {}:
            del o["metadata"]["labels"]
    rep.ok(f"kubectl decodes {len(objs)} objects: " + ", ".join(f"{o['kind']}/{o['metadata']['name']}" for o in objs))
    return objs


# The fields of the Kubernetes API (v1.32) that an object of this manifest may use: a typo is
# otherwise silently dropped by a decoder that does not validate (and --validate needs a server).
K8S_FIELDS = {
    "object": {"apiVersion", "kind", "metadata", "spec"},
    "metadata": {"name", "namespace", "labels", "annotations", "generateName"},
    "PersistentVolumeClaim": {"accessModes", "resources", "storageClassName", "volumeMode", "selector", "volumeName",
                              "dataSource", "dataSourceRef", "volumeAttributesClassName"},
    "Service": {"clusterIP", "clusterIPs", "selector", "ports", "type", "publishNotReadyAddresses", "sessionAffinity",
                "sessionAffinityConfig", "ipFamilies", "ipFamilyPolicy", "internalTrafficPolicy",
                "externalTrafficPolicy", "externalIPs", "externalName", "loadBalancerIP", "loadBalancerClass",
                "loadBalancerSourceRanges", "healthCheckNodePort", "allocateLoadBalancerNodePorts",
                "trafficDistribution"},
    "ServicePort": {"name", "port", "targetPort", "protocol", "nodePort", "appProtocol"},
    "StatefulSet": {"replicas", "selector", "template", "volumeClaimTemplates", "serviceName", "podManagementPolicy",
                    "updateStrategy", "revisionHistoryLimit", "minReadySeconds", "persistentVolumeClaimRetentionPolicy",
                    "ordinals"},
    "PodTemplate": {"metadata", "spec"},
    "PodSpec": {"containers", "initContainers", "ephemeralContainers", "volumes", "restartPolicy",
                "terminationGracePeriodSeconds", "activeDeadlineSeconds", "nodeSelector", "nodeName", "affinity",
                "tolerations", "serviceAccountName", "serviceAccount", "automountServiceAccountToken", "securityContext",
                "hostname", "subdomain", "setHostnameAsFQDN", "dnsPolicy", "dnsConfig", "hostAliases",
                "imagePullSecrets", "priorityClassName", "priority", "preemptionPolicy", "topologySpreadConstraints",
                "shareProcessNamespace", "enableServiceLinks", "hostNetwork", "hostPID", "hostIPC", "hostUsers",
                "schedulerName", "runtimeClassName", "overhead", "readinessGates", "os", "schedulingGates",
                "resourceClaims", "resources"},
    "Container": {"name", "image", "command", "args", "workingDir", "ports", "envFrom", "env", "resources",
                  "resizePolicy", "restartPolicy", "volumeMounts", "volumeDevices", "livenessProbe", "readinessProbe",
                  "startupProbe", "lifecycle", "terminationMessagePath", "terminationMessagePolicy",
                  "imagePullPolicy", "securityContext", "stdin", "stdinOnce", "tty"},
    "EnvVar": {"name", "value", "valueFrom"},
    "ContainerPort": {"containerPort", "name", "protocol", "hostPort", "hostIP"},
    "VolumeMount": {"name", "mountPath", "readOnly", "recursiveReadOnly", "subPath", "subPathExpr",
                    "mountPropagation"},
    "Resources": {"requests", "limits", "claims"},
    "Volume": {"name", "configMap", "persistentVolumeClaim", "emptyDir", "secret", "hostPath", "projected",
               "downwardAPI", "ephemeral", "csi", "nfs", "image"},
    "ConfigMapVolume": {"name", "items", "defaultMode", "optional"},
    "PVCVolume": {"claimName", "readOnly"},
    "PVCTemplate": {"metadata", "spec"},
}


def unknown_fields(rep, where, obj, kind):
    extra = sorted(set(obj) - K8S_FIELDS[kind])
    if extra:
        rep.fail(f"{where}: fields the Kubernetes API's {kind} does not have: {extra}")
    return not extra


def k8s_expand(s: str, env: dict[str, str]) -> str:
    """The kubelet's expansion of a command, an argument or an env value
    (k8s.io/kubernetes third_party/forked/golang/expansion, and the API's documentation of
    `command`/`args`): `$(NAME)` becomes NAME's value where the container defines NAME, else
    stays as it is; `$$` becomes `$` (so `$$(NAME)` stays the literal `$(NAME)`); a `$` before
    anything else, and an unclosed `$(`, stay as they are."""
    out, i = [], 0
    while i < len(s):
        c = s[i]
        if c != "$" or i + 1 >= len(s):
            out.append(c)
            i += 1
            continue
        nxt = s[i + 1]
        if nxt == "$":
            out.append("$")
            i += 2
        elif nxt == "(":
            close = s.find(")", i + 2)
            if close < 0:
                out.append("$(")
                i += 2
            else:
                name = s[i + 2:close]
                out.append(env[name] if name in env else s[i:close + 1])
                i = close + 1
        else:
            out.append("$" + nxt)
            i += 2
    return "".join(out)


def references(s: str) -> list[tuple[str, str]]:
    """Every `$(…)` the kubelet would look at, with what becomes of it: ('escaped', text) for
    `$$(…)`, ('ref', NAME) for `$(NAME)`."""
    found, i = [], 0
    while i < len(s) - 1:
        if s[i] == "$" and s[i + 1] == "$":
            if s[i + 2:i + 3] == "(":
                close = s.find(")", i + 3)
                found.append(("escaped", s[i + 1:close + 1] if close > 0 else s[i + 1:]))
            i += 2
        elif s[i] == "$" and s[i + 1] == "(":
            close = s.find(")", i + 2)
            found.append(("ref", s[i + 2:close] if close > 0 else s[i + 2:]))
            i += 2
        else:
            i += 1
    return found


def container_env(c: dict) -> tuple[dict, list[str]]:
    """The container's env as the kubelet builds it (each value expanded with the ones before it)."""
    env, unresolved = {}, []
    for e in c.get("env", []):
        if "value" in e:
            env[e["name"]] = k8s_expand(e["value"], env)
        elif "valueFrom" in e:
            unresolved.append(e["name"])
        else:
            env[e["name"]] = ""
    return env, unresolved


def static_checks(objs: list[dict], manifest: Path, rep: Report) -> dict | None:
    """The manifest's structure. Returns what the run needs to know, or None."""
    by_kind: dict[str, list[dict]] = {}
    for o in objs:
        by_kind.setdefault(o["kind"], []).append(o)
        unknown_fields(rep, f"{o['kind']}/{o['metadata']['name']}", o, "object")
        unknown_fields(rep, f"{o['kind']}/{o['metadata']['name']}.metadata", o["metadata"], "metadata")
    for kind in ("PersistentVolumeClaim", "Service", "StatefulSet"):
        if len(by_kind.get(kind, [])) != 1:
            rep.fail(f"expected one {kind}, found {len(by_kind.get(kind, []))}")
            return None
    pvc, svc, sts = by_kind["PersistentVolumeClaim"][0], by_kind["Service"][0], by_kind["StatefulSet"][0]
    rep.check(sts.get("apiVersion") == "apps/v1", "StatefulSet is apps/v1", sts.get("apiVersion"))
    rep.check(svc.get("apiVersion") == "v1" and pvc.get("apiVersion") == "v1", "Service and PVC are v1")
    unknown_fields(rep, "PersistentVolumeClaim.spec", pvc["spec"], "PersistentVolumeClaim")
    unknown_fields(rep, "Service.spec", svc["spec"], "Service")
    for p in svc["spec"].get("ports", []):
        unknown_fields(rep, "Service.spec.ports[]", p, "ServicePort")
    spec = sts["spec"]
    unknown_fields(rep, "StatefulSet.spec", spec, "StatefulSet")
    unknown_fields(rep, "StatefulSet.spec.template", spec["template"], "PodTemplate")
    pod = spec["template"]["spec"]
    unknown_fields(rep, "pod spec", pod, "PodSpec")
    labels = spec["template"].get("metadata", {}).get("labels", {})
    sts_name, svc_name = sts["metadata"]["name"], svc["metadata"]["name"]

    # The Service and the StatefulSet
    rep.check(spec.get("serviceName") == svc_name, f"StatefulSet.serviceName names the Service ({svc_name})",
              spec.get("serviceName"))
    rep.check(svc["spec"].get("clusterIP") == "None", "the Service is headless (clusterIP: None): one DNS name per pod")
    sel = svc["spec"].get("selector", {})
    rep.check(bool(sel) and all(labels.get(k) == v for k, v in sel.items()),
              f"the Service selects the pods' labels ({sel} within {labels})")
    msel = spec.get("selector", {}).get("matchLabels", {})
    rep.check(bool(msel) and all(labels.get(k) == v for k, v in msel.items()),
              f"the StatefulSet's selector matches its template's labels ({msel})")
    if svc["spec"].get("publishNotReadyAddresses"):
        rep.ok("the Service publishes pods that are not ready (publishNotReadyAddresses): a router finds its peers' "
               "names while their shard containers are down or restarting")
    else:
        rep.warn("the Service does not set publishNotReadyAddresses: a pod whose shard container is down or in "
                 "back-off is not ready, so its DNS name (twinswarm-shard-K.twinswarm-routers) is withdrawn and "
                 "routers that start meanwhile cannot resolve it")
    rep.check(pod.get("restartPolicy", "Always") == "Always", "restartPolicy Always (a StatefulSet allows no other)")
    pmp = spec.get("podManagementPolicy", "OrderedReady")
    (rep.ok if pmp == "Parallel" else rep.warn)(
        f"podManagementPolicy {pmp}" + ("" if pmp == "Parallel" else ": pods start one after the other, each "
                                                                     "waiting for the one before to be ready"))

    # Containers
    containers = {c["name"]: c for c in pod["containers"]}
    for c in pod["containers"]:
        unknown_fields(rep, f"container {c['name']}", c, "Container")
        for e in c.get("env", []):
            unknown_fields(rep, f"container {c['name']} env", e, "EnvVar")
        for p in c.get("ports", []):
            unknown_fields(rep, f"container {c['name']} ports", p, "ContainerPort")
        for m in c.get("volumeMounts", []):
            unknown_fields(rep, f"container {c['name']} volumeMounts", m, "VolumeMount")
        if "resources" in c:
            unknown_fields(rep, f"container {c['name']} resources", c["resources"], "Resources")
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    for v in pod.get("volumes", []):
        unknown_fields(rep, f"volume {v['name']}", v, "Volume")
        if "configMap" in v:
            unknown_fields(rep, f"volume {v['name']}.configMap", v["configMap"], "ConfigMapVolume")
        if "persistentVolumeClaim" in v:
            unknown_fields(rep, f"volume {v['name']}.persistentVolumeClaim", v["persistentVolumeClaim"], "PVCVolume")
    templates = {t["metadata"]["name"]: t for t in spec.get("volumeClaimTemplates", [])}
    for t in templates.values():
        unknown_fields(rep, f"volumeClaimTemplate {t['metadata']['name']}", t, "PVCTemplate")
        unknown_fields(rep, f"volumeClaimTemplate {t['metadata']['name']}.spec", t["spec"], "PersistentVolumeClaim")
    declared = set(volumes) | set(templates)
    rep.check(not (set(volumes) & set(templates)), "no volume is declared twice (volumes and volumeClaimTemplates)")

    scripts = {}
    for name, c in containers.items():
        env, unresolved = container_env(c)
        if unresolved:
            rep.warn(f"container {name}: env {unresolved} come from valueFrom; not known here")
        argv = [k8s_expand(a, env) for a in c.get("command", []) + c.get("args", [])]
        raw = "\n".join(c.get("command", []) + c.get("args", []))
        refs = references(raw)
        kept = [r for kind, r in refs if kind == "ref" and r not in env]
        used = [r for kind, r in refs if kind == "ref" and r in env]
        esc = [r[:24] + ("…" if len(r) > 24 else "") for kind, r in refs if kind == "escaped"]
        rep.info(f"container {name}: $(VAR) references expanded from env: {used or 'none'}; left literal "
                 f"(no such env): {kept or 'none'}; escaped $$(…) reaching the shell as $(…): {esc or 'none'}")
        if kept:
            rep.warn(f"container {name}: {kept} look like Kubernetes references but name no env var; the kubelet "
                     "passes them on unchanged (write $$( for a shell command substitution)")
        if c.get("command", [])[:2] != ["/bin/sh", "-c"] or len(argv) != 3:
            rep.fail(f"container {name}: expected command [/bin/sh, -c] and one script argument, got {argv[:2]}…")
            return None
        scripts[name] = argv[2]
        mounts = c.get("volumeMounts", [])
        for m in mounts:
            rep.check(m["name"] in declared, f"container {name}: volumeMount {m['name']} ({m['mountPath']}) names a "
                                             "declared volume", f"declared: {sorted(declared)}")
        paths = [m["mountPath"] for m in mounts]
        rep.check(len(paths) == len(set(paths)), f"container {name}: no two mounts at one path")
        # Absolute paths the script uses (outside the image's own /bin, /usr, /dev, /proc, /tmp)
        for p in sorted(set(re.findall(r"(?<![\w.-])(/[A-Za-z0-9_./-]+)", argv[2]))):
            if re.match(r"/(bin|usr|dev|proc|tmp|etc)(/|$)", p) or p.startswith("/0.0.0.0") or p.startswith("/twinswarm-"):
                continue
            under = [m for m in mounts if p == m["mountPath"] or p.startswith(m["mountPath"].rstrip("/") + "/")]
            rep.check(bool(under), f"container {name}: {p} lies on a mounted volume"
                      + (f" ({under[0]['name']} at {under[0]['mountPath']})" if under else ""),
                      f"mounts: {paths}")

    shard_c = next((c for c in containers.values() if "twinswarm run" in scripts[c["name"]]), None)
    router_c = next((c for c in containers.values() if "twinswarm router" in scripts[c["name"]]), None)
    if not shard_c or not router_c:
        rep.fail("expected a container running `twinswarm router` and one running `twinswarm run`")
        return None
    shard_s, router_s = scripts[shard_c["name"]], scripts[router_c["name"]]

    # The N the scripts hard-code
    replicas = spec.get("replicas", 1)
    ns = {("--shard $K/N", int(n)) for n in re.findall(r"--shard \$K/(\d+)", shard_s)}
    ns |= {("-of-N", int(n)) for n in re.findall(r"-of-(\d+)", shard_s)}
    ns |= {("awk '$1 == N'", int(n)) for n in re.findall(r"\$1 == (\d+)", shard_s)}
    loop = re.search(r"for j in ([0-9 ]+); do", router_s)
    js = [int(x) for x in loop.group(1).split()] if loop else []
    rep.check(bool(ns) and all(n == replicas for _w, n in ns),
              f"StatefulSet replicas ({replicas}) = the N of the shard script ({sorted(ns)})")
    rep.check(js == list(range(replicas)), f"the router's loop `for j in …` ({js}) covers the pods 0..{replicas - 1}")

    # Ports and names: the routers listen on the port the Service and the other routers use
    svc_ports = [p["port"] for p in svc["spec"].get("ports", [])]
    cports = [p["containerPort"] for p in router_c.get("ports", [])]
    listen = re.findall(r"--listen tcp/([0-9.]+):(\d+)", router_s)
    connect = re.findall(r"--connect tcp/([^\s:]+):(\d+)", router_s)
    rep.check(len(listen) == 1 and listen[0][0] == "0.0.0.0", "the router listens on every address of its pod",
              str(listen))
    port = int(listen[0][1]) if listen else None
    rep.check(port in svc_ports and port in cports,
              f"the router's port ({port}) is the Service's ({svc_ports}) and the container's ({cports})")
    want = f"{sts_name}-$j.{svc_name}"
    rep.check(len(connect) == 1 and connect[0] == (want, str(port)),
              f"each router connects to the others by their pod DNS names {want}:{port}", str(connect))
    sconnect = re.findall(r"--connect (tcp/127\.0\.0\.1:(\d+))", shard_s)
    rep.check(len(sconnect) == 1 and int(sconnect[0][1]) == port,
              f"the shard connects to its own pod's router (127.0.0.1:{port})", str(sconnect))
    rep.check("${HOSTNAME##*-}" in shard_s and "${HOSTNAME##*-}" in router_s,
              "both scripts take K from the pod's hostname (the StatefulSet ordinal)")

    # Volumes the shard uses
    smounts = {m["name"]: m["mountPath"] for m in shard_c.get("volumeMounts", [])}
    cdir = re.search(r"\bC=(\S+?);", shard_s)
    ck_mount = next((n for n, p in smounts.items() if cdir and p == cdir.group(1)), None)
    rep.check(ck_mount is not None, f"the checkpoint directory C={cdir.group(1) if cdir else '?'} is a mount "
                                    f"({ck_mount})")
    if ck_mount:
        claim = volumes.get(ck_mount, {}).get("persistentVolumeClaim", {}).get("claimName")
        rep.check(claim == pvc["metadata"]["name"], f"the checkpoint volume is the manifest's PVC ({claim})")
        modes = pvc["spec"].get("accessModes", [])
        rep.check("ReadWriteMany" in modes, f"the checkpoint PVC is ReadWriteMany (every pod reads every shard's "
                                            f"checkpoints): {modes}")
    rep.check("--checkpoint-dir $C" in shard_s, "the shard writes its checkpoints into $C")
    every = re.search(r"--checkpoint-every (\S+)", shard_s)
    rep.info(f"checkpoints every {every.group(1) if every else '?'} simulated s (`twinswarm run --help`: "
             "--checkpoint-every S is simulated seconds)")
    logm = re.search(r"--log (/\S+)/shard-", shard_s)
    log_mount = next((n for n, p in smounts.items() if logm and p == logm.group(1)), None)
    rep.check(log_mount in templates, f"the logs go to a per-pod volume (volumeClaimTemplate {log_mount})")
    scene = re.search(r"twinswarm run (/\S+)", shard_s)
    scene_path = scene.group(1) if scene else ""
    scene_mount = next((n for n, p in smounts.items() if scene_path.startswith(p.rstrip("/") + "/")), None)
    cm = volumes.get(scene_mount, {}).get("configMap", {}).get("name")
    key = scene_path.rsplit("/", 1)[-1]
    header = manifest.read_text()
    made = re.search(r"kubectl create configmap (\S+) --from-file=([^=\s]+)=", header)
    rep.check(bool(made) and made.group(1) == cm and made.group(2) == key,
              f"the scene {scene_path} is key {key!r} of ConfigMap {cm!r}, as the header's `kubectl create configmap` "
              f"makes it", made.group(0) if made else "no `kubectl create configmap` in the header")

    # The log epoch
    env, _ = container_env(shard_c)
    epoch = env.get("TWINSWARM_LOG_EPOCH_NS")
    rep.check(epoch is not None and epoch.isdigit(), f"TWINSWARM_LOG_EPOCH_NS set on the shard container ({epoch})")

    # The image
    images = {c["image"] for c in pod["containers"]}
    rep.check(len(images) == 1, f"both containers run one image ({images})")
    for c in pod["containers"]:
        image, policy = c["image"], c.get("imagePullPolicy")
        latest = ":" not in image.rsplit("/", 1)[-1] or image.endswith(":latest")
        if latest and policy is None:
            rep.warn(f"container {c['name']}: image {image} with no imagePullPolicy: Kubernetes defaults to Always "
                     "for :latest, so every node pulls docker.io/library/twinswarm:latest, which is not where "
                     "`podman build -t twinswarm` puts it")
        else:
            rep.ok(f"container {c['name']}: image {image}, imagePullPolicy {policy or 'IfNotPresent (default)'}")
    return {
        "replicas": replicas, "sts": sts_name, "svc": svc_name, "port": port, "epoch": epoch,
        "containers": pod["containers"], "router": router_c["name"], "shard": shard_c["name"],
        "volumes": volumes, "templates": templates, "scripts": scripts, "ckpt_mount": ck_mount,
        "log_mount": log_mount, "scene_mount": scene_mount, "scene_key": key,
    }


def image_checks(rep: Report, bin_path: Path):
    """What can be said about deploy/Containerfile without building it."""
    info = subprocess.run(["docker", "info"], capture_output=True, text=True) if shutil.which("docker") else None
    if info is None:
        rep.info("image build not checked: no docker client")
    elif info.returncode != 0 or "Cannot connect" in info.stderr:
        rep.info("image build not checked: `docker info` finds no daemon ("
                 + next((l.strip() for l in info.stderr.splitlines() if l.strip()), "?")
                 + "), and a build would need to pull rust:1-bookworm and debian:bookworm-slim (no network here)")
    else:
        rep.info("a docker daemon answers, but the build pulls its base images (no network here): not tried")
    cf = (ROOT / "deploy/Containerfile").read_text()
    rep.check("debian:bookworm-slim" in cf, "the runtime image is Debian bookworm-slim")
    # The shard script's tools: dash, coreutils, sed, mawk are Priority: required in Debian, so in -slim.
    q = subprocess.run(["dpkg-query", "-W", "-f=${Package} ${Priority}\\n", "dash", "coreutils", "sed", "mawk"],
                       capture_output=True, text=True)
    if q.returncode == 0:
        rep.info("the scripts' tools here (Debian 12, as the image): " + ", ".join(q.stdout.split("\n")[:-1])
                 + " (Priority required: in bookworm-slim)")
    ldd = subprocess.run(["ldd", str(bin_path)], capture_output=True, text=True)
    libs = re.findall(r"=> (/\S+)", ldd.stdout)
    pkgs = set()
    for lib in libs:
        s = subprocess.run(["dpkg", "-S", os.path.realpath(lib)], capture_output=True, text=True).stdout
        s = s or subprocess.run(["dpkg", "-S", lib], capture_output=True, text=True).stdout
        pkgs |= {s.split(":")[0]} if s else {f"? {lib}"}
    if pkgs:
        # In -slim: the Priority-required and Essential packages and what they depend on.
        q = subprocess.run(["dpkg-query", "-W", "-f=${Package}\t${Priority}\t${Essential}\t${Pre-Depends}, ${Depends}\n"],
                           capture_output=True, text=True).stdout
        deps, base = {}, set()
        for line in q.splitlines():
            name, prio, ess, dep = line.split("\t")
            deps[name] = {re.split(r"[\s:(]", d.strip())[0] for alt in dep.split(",") for d in alt.split("|")[:1] if d.strip()}
            if prio == "required" or ess == "yes":
                base.add(name)
        todo = list(base)
        while todo:
            for d in deps.get(todo.pop(), ()):
                if d in deps and d not in base:
                    base.add(d)
                    todo.append(d)
        rep.check(all(p in base for p in pkgs),
                  f"the binary's shared libraries come from {sorted(pkgs)}, all in Debian's required set and its "
                  "dependencies (so in bookworm-slim): a bookworm build runs there",
                  f"not: {sorted(p for p in pkgs if p not in base)}")


# ----------------------------------------------------------------------------- step 2: pods
def free_port_block(n: int) -> int:
    """A base such that base..base+n-1 are free on 127.0.0.1 right now."""
    for _ in range(200):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + n > 65535:
            continue
        socks = []
        try:
            for p in range(base, base + n):
                t = socket.socket()
                socks.append(t)
                t.bind(("127.0.0.1", p))
            return base
        except OSError:
            pass
        finally:
            for t in socks:
                t.close()
    raise RuntimeError("no block of free loopback ports")


def common_tick(ckdir: Path, n: int) -> str | None:
    """The shard script's rule, in Python: the newest tick with all N checkpoints."""
    ticks: dict[str, int] = {}
    for f in ckdir.iterdir() if ckdir.exists() else []:
        m = re.fullmatch(rf"shard-\d+-of-{n}-tick-(\d+)\.ckpt", f.name)
        if m:
            ticks[m.group(1)] = ticks.get(m.group(1), 0) + 1
    full = sorted(t for t, c in ticks.items() if c == n)
    return full[-1] if full else None


class Start:
    def __init__(self, n, out, err, expected_tick):
        self.n, self.out, self.err = n, out, err
        self.expected_tick = expected_tick
        self.t_start, self.t_end, self.rc, self.pid = time.monotonic(), None, None, None

    def summary(self):
        """The run's JSON summary (what the script echoes after it is left out)."""
        try:
            text = self.out.read_text()
            return json.JSONDecoder().raw_decode(text, text.index("{"))[0]
        except (OSError, ValueError):
            return None


class Container(threading.Thread):
    """One container of a pod under restartPolicy Always: started when its pod is up, started
    again when it exits (after the kubelet's back-off, 10 s doubling to 300 s, times `scale`)."""

    def __init__(self, pod, name, argv, env, cwd, scale, ckdir, n):
        super().__init__(daemon=True)
        self.pod, self.name, self.argv, self.env, self.cwd = pod, name, argv, env, cwd
        self.scale, self.ckdir, self.n = scale, ckdir, n
        self.starts: list[Start] = []
        self.proc = None
        self.gate = threading.Event()   # set while the pod is up
        self.lock = threading.Lock()
        self.restarts_in_pod = 0

    def run(self):
        while not self.pod.cluster.stopping.is_set():
            self.gate.wait()
            if self.pod.cluster.stopping.is_set():
                break
            k = len(self.starts) + 1
            out = self.pod.dir / f"{self.name}.{k}.out"
            err = self.pod.dir / f"{self.name}.{k}.err"
            st = Start(k, out, err, common_tick(self.ckdir, self.n) if self.name == self.pod.cluster.shard_name else None)
            with self.lock:
                if not self.gate.is_set() or self.pod.cluster.stopping.is_set():
                    continue
                self.proc = subprocess.Popen(self.argv, env=self.env, cwd=self.cwd, stdout=out.open("wb"),
                                             stderr=err.open("wb"), start_new_session=True)
                st.pid = self.proc.pid
                self.starts.append(st)
            st.rc = self.proc.wait()
            st.t_end = time.monotonic()
            self.pod.cluster.event(f"pod {self.pod.k} {self.name} #{k} exited {st.rc}")
            if self.pod.cluster.stopping.is_set() or not self.gate.is_set():
                continue   # stopped, or the pod died: a new pod starts it afresh
            self.restarts_in_pod += 1
            delay = min(10 * 2 ** (self.restarts_in_pod - 1), 300) * self.scale
            self.pod.cluster.stopping.wait(max(delay, 1.0))

    def kill(self, sig):
        with self.lock:
            if self.proc and self.proc.poll() is None:
                try:
                    os.killpg(self.proc.pid, sig)
                except ProcessLookupError:
                    pass


class Pod:
    def __init__(self, cluster, k):
        self.cluster, self.k = cluster, k
        self.dir = cluster.work / f"pod-{k}"
        self.dir.mkdir(parents=True)
        self.containers: list[Container] = []

    def up(self):
        """A pod (re)starts: the kubelet starts its containers in the spec's order."""
        for c in self.containers:
            c.restarts_in_pod = 0
            c.gate.set()
            time.sleep(self.cluster.start_gap)

    def kill(self, sig=signal.SIGKILL):
        """The machine dies: every process of the pod SIGKILLed (its sockets close at once), or
        SIGSTOPped (a machine that stops answering: its peers notice only when Zenoh's lease
        runs out); nothing restarts it."""
        for c in self.containers:
            c.gate.clear()
        for c in self.containers:
            c.kill(sig)


class Cluster:
    """The StatefulSet's pods on loopback."""

    def __init__(self, model, work, bin_path, scene, rep, scale, start_gap, json_flag=True):
        self.model, self.work, self.rep = model, work, rep
        self.stopping = threading.Event()
        self.start_gap = start_gap
        self.shard_name = model["shard"]
        self.n = model["replicas"]
        self.events: list[tuple[float, str]] = []
        self.t0 = time.monotonic()
        bindir = work / "bin"
        bindir.mkdir()
        (bindir / "twinswarm").symlink_to(bin_path)
        # Volumes: the ConfigMap and the RWX PVC are one directory for all pods; a
        # volumeClaimTemplate is one directory per pod; the image's WORKDIR one per container.
        shared = {}
        for name, v in model["volumes"].items():
            d = work / "volumes" / name
            d.mkdir(parents=True)
            if "configMap" in v:
                shutil.copy(scene, d / model["scene_key"])
            shared[name] = d
        self.ckdir = shared[model["ckpt_mount"]]
        self.base = free_port_block(self.n)
        port = model["port"]
        self.subs_listed = []
        self.pods = []
        for k in range(self.n):
            pod = Pod(self, k)
            self.pods.append(pod)
            for c in model["containers"]:
                env, _ = container_env(c)
                script = model["scripts"][c["name"]]
                subs = []
                if c["name"] == model["router"]:
                    subs += [(f"tcp/0.0.0.0:{port}", f"tcp/127.0.0.1:{self.base + k}",
                              "the router's listen address: the pod's own port on loopback"),
                             (f"tcp/{model['sts']}-$j.{model['svc']}:{port}", f"tcp/127.0.0.1:$(({self.base} + $j))",
                              "the other pods' DNS names: their loopback ports")]
                else:
                    subs += [(f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{self.base + k}",
                              "localhost:7447 (the pod's own router): that pod's loopback port")]
                    if json_flag:
                        subs += [("twinswarm run ", "twinswarm run --json ",
                                  "`--json` for the per-copter digests (the text summary has none)")]
                for old, new, why in subs:
                    count = script.count(old)
                    script = script.replace(old, new)
                    if count == 0:
                        rep.fail(f"substitution {old!r} not found in container {c['name']}'s script")
                    if k == 0:
                        self.subs_listed.append((c["name"], old, new.replace(str(work), "$WORK"), count, why))
                # Mount paths: one pass, whole path components only (/var/lib/twinswarm is a prefix
                # of /var/lib/twinswarm-checkpoints).
                where = {}
                for m in c.get("volumeMounts", []):
                    d = shared.get(m["name"])
                    if d is None:   # a volumeClaimTemplate: the pod's own
                        d = pod.dir / "volumes" / m["name"]
                        d.mkdir(parents=True, exist_ok=True)
                    where[m["mountPath"]] = (str(d), m["name"])
                if where:
                    alt = "|".join(re.escape(x) for x in sorted(where, key=len, reverse=True))
                    pattern = re.compile(rf"(?<![\w./-])({alt})(?![\w.-])")
                    counts = {x: len([1 for mm in pattern.finditer(script) if mm.group(1) == x]) for x in where}
                    script = pattern.sub(lambda mm: where[mm.group(1)][0], script)
                    if k == 0:
                        for x, (d, vname) in where.items():
                            self.subs_listed.append((c["name"], x, d.replace(str(work), "$WORK"), counts[x],
                                                     f"volume {vname} mounted at {x}"))
                cwd = pod.dir / f"{c['name']}-workdir"   # the image's WORKDIR /var/lib/twinswarm
                cwd.mkdir(exist_ok=True)
                for m in c.get("volumeMounts", []):
                    if m["mountPath"] == "/var/lib/twinswarm":
                        cwd = shared.get(m["name"], pod.dir / "volumes" / m["name"])
                full_env = {"PATH": f"{bindir}:/usr/local/bin:/usr/bin:/bin", "HOSTNAME": f"{model['sts']}-{k}",
                            "HOME": str(pod.dir), **env}
                argv = [c["command"][0], c["command"][1], script]
                if k == 0:
                    (work / f"{c['name']}.pod0.sh").write_text(script + "\n")
                pod.containers.append(Container(pod, c["name"], argv, full_env, cwd, scale, self.ckdir, self.n))

    def event(self, msg):
        self.events.append((time.monotonic() - self.t0, msg))

    def start(self):
        for p in self.pods:
            for c in p.containers:
                c.start()
        for p in self.pods:   # Parallel: every pod at once (each pod's containers in order)
            threading.Thread(target=p.up, daemon=True).start()

    def shard(self, k) -> Container:
        return next(c for c in self.pods[k].containers if c.name == self.shard_name)

    def logs(self, k) -> list[Path]:
        return sorted((self.pods[k].dir / "volumes" / self.model["log_mount"]).glob("*.mcap"))

    def finished(self, k, duration):
        """The shard's start that ran to the end of the run, if any."""
        for st in self.shard(k).starts:
            s = st.summary()
            if s and not s.get("interrupted") and abs(s.get("sim_time_s", -1) - duration) < 1e-6 and st.rc in (None, 0):
                return st
        return None

    def stop(self):
        """The pods deleted: SIGTERM to each container's main process (PID 1 in a pod, which
        ignores a signal it has no handler for), SIGKILL after a grace. Returns each main
        process's exit status after the SIGTERM ({(pod, container): rc or None})."""
        self.stopping.set()
        procs = {}
        for p in self.pods:
            for c in p.containers:
                c.gate.set()
                with c.lock:
                    if c.proc and c.proc.poll() is None:
                        procs[(p.k, c.name)] = c.proc
                        c.proc.send_signal(signal.SIGTERM)
        end = time.monotonic() + 5
        while time.monotonic() < end and any(pr.poll() is None for pr in procs.values()):
            time.sleep(0.05)
        status = {k: pr.poll() for k, pr in procs.items()}
        for p in self.pods:
            for c in p.containers:
                c.kill(signal.SIGKILL)
        for p in self.pods:
            for c in p.containers:
                c.join(5)
        return status


# ----------------------------------------------------------------------------- logs
def log_states(path: Path):
    """{(tick, id): (bytes, body without tick/t_s)} of /copters/state, CRCs validated."""
    from google.protobuf.json_format import MessageToDict
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    factory, decoders, states, dup = DecoderFactory(), {}, {}, 0
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f, validate_crcs=True).iter_messages(
                topics=["/copters/state"], log_time_order=False):
            if schema.id not in decoders:
                decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
            proto = decoders[schema.id](message.data)
            key = (int(proto.tick), int(proto.id))
            dup += key in states
            states[key] = message.data
    return states, dup, decoders, MessageToDict


def compare_logs(rep, merged: Path, one: Path):
    try:
        import mcap  # noqa: F401
        import mcap_protobuf  # noqa: F401
    except ImportError:
        rep.info("log comparison skipped: PyPI mcap / mcap-protobuf-support not importable (run with .venv/bin/python)")
        return
    t = time.monotonic()
    a, _, _, _ = log_states(one)
    b, dup, decoders, to_dict = log_states(merged)
    rep.check(dup == 0, f"the merged log has every (tick, copter) state once ({len(b)} states)", f"{dup} twice")
    missing = [k for k in a if k not in b]
    differ = [k for k in a if k in b and a[k] != b[k]]
    rep.check(not missing and not differ,
              f"every state of the one-process log ({len(a)}, {len({i for _t, i in a})} copters, "
              f"{len({t for t, _i in a})} steps) is in the merged log with its bytes",
              f"{len(missing)} missing (first {sorted(missing)[:3]}), {len(differ)} differ (first {sorted(differ)[:3]})")
    extra = sorted(b.keys() - a.keys())
    if extra:
        # A shard writes a copter again on the step it takes it over (or restarts), where the
        # one-process log holds it: the held values with that step's tick (docs/sharding.md, Logs).
        dec = next(iter(decoders.values()))
        held_ok = 0
        by_copter: dict[int, list[int]] = {}
        for tk, i in a:
            by_copter.setdefault(i, []).append(tk)
        for tk in by_copter.values():
            tk.sort()
        for tick, i in extra:
            before = [x for x in by_copter.get(i, []) if x < tick]
            if not before:
                continue
            strip = lambda d: {k: v for k, v in to_dict(dec(d)).items() if k not in ("tick", "tS", "t_s")}
            held_ok += strip(b[(tick, i)]) == strip(a[(before[-1], i)])
        rep.check(held_ok == len(extra), f"the merged log's {len(extra)} states the one-process log holds are the held "
                                         "ones (a shard writes a copter it takes over or restarts with)",
                  f"{len(extra) - held_ok} are not")
    rep.info(f"log comparison took {time.monotonic() - t:.1f} s")


# ----------------------------------------------------------------------------- the run
def digests_of(copters):
    return {c["id"]: c["digest"] for c in copters}


def one_process(args, rep, work, bin_path):
    """The scene, and the uninterrupted one-process run's digests (and log)."""
    rep.section("the scene and the uninterrupted one-process run")
    scene = work / "scene.toml"
    text = subprocess.run([str(bin_path), "scene", args.kind, "--n", str(args.n), "--seed", str(args.seed)],
                          check=True, capture_output=True, text=True).stdout
    text, count = re.subn(r"(?m)^duration_s = .*$", f"duration_s = {args.duration:.1f}", text, count=1)
    assert count == 1, "no duration_s in the scene"
    scene.write_text(text)
    rep.info(f"scene: `twinswarm scene {args.kind} --n {args.n} --seed {args.seed}`, sim.duration_s = {args.duration} "
             "(the manifest's shard command passes no --duration)")
    one = subprocess.run([str(bin_path), "run", str(scene), "--no-bus", "--no-log", "--json"],
                         capture_output=True, text=True)
    if not rep.check(one.returncode == 0, "one-process run (run SCENE --no-bus --no-log --json)", one.stderr[-500:]):
        return None
    one_log = work / "one.mcap"
    if args.logs:
        subprocess.run([str(bin_path), "run", str(scene), "--no-bus", "--log", str(one_log)],
                       check=True, capture_output=True)
    return scene, digests_of(json.loads(one.stdout)["copters"]), one_log


def run_pods(args, model, rep, work, bin_path, fault: bool, base):
    scene, one_digests, one_log = base
    control_dt = float(re.search(r"(?m)^control_dt_s = (\S+)", scene.read_text()).group(1))
    work.mkdir()
    rep.section(f"{model['replicas']} pods on loopback" + (
        f": pod {args.kill_pod} {'SIGKILLed' if args.fault == 'kill' else 'SIGSTOPped'}, back {args.dead_s} s later"
        if fault else ""))
    cl = Cluster(model, work, bin_path, scene, rep, args.backoff_scale, args.start_gap)
    rep.info(f"work directory {work}; pods' router ports 127.0.0.1:{cl.base}..{cl.base + cl.n - 1}")
    rep.info("what differs from the pods' scripts (each with its count in the script it changes):")
    for cname, old, new, count, why in cl.subs_listed:
        rep.info(f"  [{cname}] {old!r} -> {new!r} (x{count}): {why}")
    rep.info("  HOSTNAME=twinswarm-shard-K per pod; PATH starts with a directory whose `twinswarm` links to "
             f"{bin_path}; the working directory is the image's WORKDIR /var/lib/twinswarm (mapped as above); "
             "the kubelet's restart back-off (10 s doubling) is scaled by "
             f"{args.backoff_scale} (at least 1 s); a dead pod stays down {args.dead_s} s")
    rep.info(f"the shard script as pod 0 runs it: {(work / (model['shard'] + '.pod0.sh'))}")
    t_start = time.monotonic()
    cl.start()
    n = cl.n
    deadline = t_start + args.timeout
    killed_at, victim, tick_at_kill, neighbours_exit, done = None, args.kill_pod, None, {}, {}
    try:
        if fault:
            # Once every shard has a checkpoint (a common tick), wait a little and kill a pod.
            while time.monotonic() < deadline and common_tick(cl.ckdir, n) is None:
                time.sleep(0.05)
            first = common_tick(cl.ckdir, n)
            if not rep.check(first is not None, "every shard wrote a checkpoint"):
                return
            rep.info(f"checkpoints of every shard at tick {int(first)}; killing pod {victim} in {args.kill_after} s")
            time.sleep(args.kill_after)
            running = {k: cl.shard(k).starts[-1] for k in range(n) if cl.shard(k).starts}
            sig = signal.SIGKILL if args.fault == "kill" else signal.SIGSTOP
            cl.pods[victim].kill(sig)
            killed_at = time.monotonic()
            cl.event(f"pod {victim} killed ({sig.name} router and shard)")
            rep.info(f"pod {victim}: router and shard {sig.name}ed ({killed_at - t_start:.1f} s after the start)")

            def revive():
                if sig != signal.SIGKILL:   # the old pod is deleted before the new one starts
                    cl.pods[victim].kill(signal.SIGKILL)
                cl.event(f"pod {victim} up again")
                rep.info(f"pod {victim} starts again, {time.monotonic() - killed_at:.1f} s after the kill (a new "
                         "pod: its containers in order)")
                cl.pods[victim].up()

            reviver = threading.Timer(args.dead_s, revive)
            reviver.start()
            # Its neighbours must stop on their own.
            for k in range(n):
                if k == victim:
                    continue
                st = running.get(k)
                while time.monotonic() < killed_at + args.barrier_wait and st and st.rc is None:
                    time.sleep(0.05)
                if st and st.rc is not None:
                    err = st.err.read_text(errors="replace")
                    left = re.search(r"shard (\d+) left the cluster at tick (\d+)", err)
                    silent = re.search(r"no word from shard\(s\) \[[^]]*\b%d\b[^]]*\] for [0-9.]+ s" % victim, err)
                    after = st.t_end - killed_at
                    neighbours_exit[k] = (after, st.rc, left.group(0) if left else None)
                    if left and int(left.group(1)) == victim and st.rc != 0:
                        rep.ok(f"shard {k} stopped on its own {after:.1f} s after the kill (exit {st.rc}: "
                               f"{left.group(0)})")
                    elif silent and st.rc != 0:
                        # Its router kept the dead shard's liveliness token (a Zenoh router mesh
                        # losing a router; docs/sharding.md): the barrier timeout stops it.
                        router_err = "".join(c.starts[0].err.read_text(errors="replace")
                                             for c in cl.pods[k].containers if c.name == model["router"])
                        lost = len(re.findall(r"cannot get index of", router_err))
                        rep.warn(f"shard {k} stopped only at its barrier timeout, {after:.1f} s after the kill "
                                 f"({silent.group(0)}): its router kept the dead shard's liveliness token"
                                 + (f" (the router logged {lost} `Error propagating …: cannot get index of <zid>`)"
                                    if lost else ""))
                    else:
                        rep.fail(f"shard {k} stopped {after:.1f} s after the kill, exit {st.rc}, neither for the "
                                 "dead neighbour nor at its barrier timeout")
                else:
                    rep.fail(f"shard {k} did not stop within {args.barrier_wait} s of the kill")
            tick_at_kill = common_tick(cl.ckdir, n)
            rep.info(f"newest tick with all {n} checkpoints once the neighbours stopped: "
                     f"{int(tick_at_kill) if tick_at_kill else None}")
            reviver.join()
        # The run must end on every pod.
        while time.monotonic() < deadline and not all(cl.finished(k, args.duration) for k in range(n)):
            time.sleep(0.1)
        done = {k: cl.finished(k, args.duration) for k in range(n)}
        t_done = time.monotonic()
        if not rep.check(all(done.values()), f"every shard ran to the end ({args.duration} s simulated)",
                         f"not: {[k for k, v in done.items() if not v]} after {args.timeout} s"):
            return
        rep.info(f"the run ended {t_done - t_start:.1f} s after the pods started")
        # … and stay ended: restartPolicy Always restarts a container that exits, even with 0.
        logs_before = {k: set(cl.logs(k)) for k in range(n)}
        starts_before = {k: len(cl.shard(k).starts) for k in range(n)}
        time.sleep(args.observe_s)
        reran = {k: sorted(p.name for p in set(cl.logs(k)) - logs_before[k]) for k in range(n)}
        restarted = {k: len(cl.shard(k).starts) - starts_before[k] for k in range(n)}
        rep.check(not any(reran.values()),
                  f"no shard runs again in the {args.observe_s} s after the end (restartPolicy Always restarts a "
                  "container that exits 0)",
                  f"restarted containers {restarted}, new logs {reran}")
        rep.info("shard containers' state after the end: " + ", ".join(
            f"{k}: {'running' if cl.shard(k).proc and cl.shard(k).proc.poll() is None else 'exited'}"
            f" ({len(cl.shard(k).starts)} starts)" for k in range(n)))
    finally:
        status = cl.stop()
    wall = time.monotonic() - t_start
    rep.info("the pods deleted: SIGTERM to each container's main process; exit status within 5 s: "
             + ", ".join(f"{k}/{c} {rc}" for (k, c), rc in sorted(status.items())))
    rep.check(all(rc is not None for rc in status.values()),
              "every container's main process ends on SIGTERM (in a pod it is PID 1: without a handler the "
              "signal is ignored and the kubelet SIGKILLs it after the grace period)",
              str({k: rc for k, rc in status.items() if rc is None}))

    rep.section("results")
    for k in range(n):
        for st in cl.shard(k).starts:
            s = st.summary()
            resumed = (s or {}).get("checkpoints", {}).get("resumed_from")
            rtick = re.search(r"tick-(\d+)\.ckpt", resumed).group(1) if resumed else None
            err = st.err.read_text(errors="replace")
            why = re.search(r"^error: (.*)$", err, re.M)
            rep.info(f"pod {k} shard start #{st.n}: exit {st.rc}, ran {((st.t_end or time.monotonic()) - st.t_start):.1f} s"
                     f", resumed from {int(rtick) if rtick else '-'} (the tick rule, in Python: "
                     f"{int(st.expected_tick) if st.expected_tick else '-'})"
                     + (f", sim {s['sim_time_s']:.2f} s" if s else ", no summary")
                     + (f"; {why.group(1)[:140]}" if why else ""))
            if s is not None:
                rep.check(rtick == st.expected_tick,
                          f"pod {k} start #{st.n} " + (f"resumed from the newest tick all {n} shards had a checkpoint for"
                                                       if st.expected_tick else "started from the beginning (no tick "
                                                       f"with all {n} checkpoints yet)"),
                          f"{rtick} != {st.expected_tick}")
    finals = done   # the starts that ran to the end (before the pods were deleted)
    if fault:
        froms = {k: (finals[k].summary() or {}).get("checkpoints", {}).get("resumed_from") for k in range(n)}
        ticks = {re.search(r"tick-(\d+)", f).group(1) if f else None for f in froms.values()}
        rep.check(len(ticks) == 1 and None not in ticks and ticks == {tick_at_kill},
                  f"every shard's last start resumed from one tick, the newest common one at the kill "
                  f"({int(tick_at_kill) if tick_at_kill else None})", str(froms))
    copters = []
    for k in range(n):
        copters += finals[k].summary()["copters"]
    ids = [c["id"] for c in copters]
    rep.check(len(ids) == len(set(ids)) == len(one_digests), f"the shards' summaries hold every copter once "
                                                              f"({len(set(ids))} of {len(one_digests)})")
    mine = digests_of(copters)
    differ = sorted(i for i in one_digests if mine.get(i) != one_digests[i])
    rep.check(not differ, f"every copter's final digest equals the uninterrupted one-process run's "
                          f"({len(one_digests) - len(differ)} of {len(one_digests)} equal)",
              f"{len(differ)} differ, first {differ[:5]}")
    rep.info(f"swarm fingerprint: one process {sorted(one_digests.items())[:2]}…, shards {sorted(mine.items())[:2]}…")

    if args.logs:
        rep.section("logs: recover, merge, compare")
        inputs = []
        for k in range(n):
            for p in cl.logs(k):
                info = subprocess.run([str(bin_path), "log", "info", str(p)], capture_output=True, text=True)
                if info.returncode == 0:
                    inputs.append(p)
                    continue
                fixed = p.with_name(p.stem + ".recovered.mcap")
                rec = subprocess.run([str(bin_path), "log", "recover", str(p), str(fixed)], capture_output=True,
                                     text=True)
                if rep.check(rec.returncode == 0, f"pod {k}: {p.name} is torn; `log recover` rescues it",
                             rec.stderr[-300:]):
                    inputs.append(fixed)
                    rep.info("   " + (rec.stdout.strip().splitlines() or [""])[-1][:200])
                    # It reaches at least the checkpoint the shards went on from (docs/sharding.md).
                    info = subprocess.run([str(bin_path), "log", "info", str(fixed)], capture_output=True, text=True)
                    span = re.search(r"([0-9.]+) s to ([0-9.]+) s simulated", info.stdout)
                    if fault and tick_at_kill and span:
                        need = int(tick_at_kill) * control_dt
                        rep.check(float(span.group(2)) + 1e-9 >= need,
                                  f"the recovered log reaches {span.group(2)} s simulated, at least the checkpoint "
                                  f"the run went on from ({need:.2f} s)")
        rep.info(f"{len(inputs)} logs: " + ", ".join(f"pod{p.parent.parent.parent.name[-1]}/{p.name}" for p in inputs))
        merged = work / "merged.mcap"
        m = subprocess.run([str(bin_path), "log", "merge", "-o", str(merged), *map(str, inputs)],
                           capture_output=True, text=True)
        if rep.check(m.returncode == 0, "`twinswarm log merge` merges every pod's logs", m.stderr[-300:]):
            compare_logs(rep, merged, one_log)
    rep.info(f"pods' part took {wall:.1f} s wall")
    (work / "events.json").write_text(json.dumps(cl.events, indent=1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=["static", "smoke", "full"], default="full")
    ap.add_argument("--manifest", type=Path, default=MANIFEST)
    ap.add_argument("--bin", type=Path, default=Path(os.environ.get("TWINSWARM_BIN", ROOT / "target/release/twinswarm")))
    ap.add_argument("--kind", default="dense", help="`twinswarm scene` kind (default dense)")
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=35.0, help="simulated s, written into the scene")
    ap.add_argument("--kill-pod", type=int, default=1)
    ap.add_argument("--kill-after", type=float, default=0.7, help="wall s after the first common checkpoint")
    ap.add_argument("--fault", choices=["kill", "freeze"], default="kill",
                    help="kill: SIGKILL the pod's processes (their sockets close); freeze: SIGSTOP them (a machine "
                         "that stops answering), SIGKILL when the pod comes back")
    ap.add_argument("--dead-s", type=float, default=5.0, help="how long the dead pod stays down, wall s")
    ap.add_argument("--quick-restart-s", type=float, default=0.5,
                    help="full: also a pod back this soon after its kill (0: not)")
    ap.add_argument("--barrier-wait", type=float, default=75.0,
                    help="how long the neighbours may take to stop (the manifest's --barrier-timeout is 60 s)")
    ap.add_argument("--backoff-scale", type=float, default=0.1, help="the kubelet's restart back-off times this")
    ap.add_argument("--start-gap", type=float, default=0.1, help="s between a pod's router and shard starts")
    ap.add_argument("--observe-s", type=float, default=4.0, help="how long to watch after the end for re-runs")
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--no-logs", dest="logs", action="store_false", help="skip log recover/merge/compare")
    ap.add_argument("--keep", action="store_true", help="keep the work directory")
    args = ap.parse_args()
    rep = Report()
    t0 = time.monotonic()
    print(f"k8s-check {args.mode}: {args.manifest.relative_to(ROOT) if args.manifest.is_relative_to(ROOT) else args.manifest}"
          f", {datetime.datetime.now().isoformat(timespec='seconds')}")
    work = Path(tempfile.mkdtemp(prefix="k8s-check-"))
    try:
        rep.section("static: the manifest as kubectl decodes it")
        objs = kubectl_decode(args.manifest, work, rep)
        model = static_checks(objs, args.manifest, rep) if objs else None
        if args.mode != "static":
            bin_path = args.bin.resolve()
            if not bin_path.exists():
                rep.fail(f"no twinswarm binary at {bin_path} (--bin or TWINSWARM_BIN)")
            else:
                rep.section("the image (deploy/Containerfile)")
                image_checks(rep, bin_path)
                base = one_process(args, rep, work, bin_path) if model else None
                if base and args.mode == "smoke":
                    run_pods(args, model, rep, work / "smoke", bin_path, False, base)
                elif base:
                    # A dead machine: its pod back after a while (in a cluster, minutes).
                    run_pods(args, model, rep, work / "dead-machine", bin_path, True, base)
                    if args.quick_restart_s > 0:
                        # A crashed container, started again at once by the kubelet (its first
                        # restart has no back-off), before its neighbours' 2 s grace is over.
                        quick = argparse.Namespace(**{**vars(args), "dead_s": args.quick_restart_s, "logs": False})
                        run_pods(quick, model, rep, work / "quick-restart", bin_path, True, base)
    finally:
        if args.keep or rep.fails:
            print(f"\nfiles kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    print(f"\nk8s-check {args.mode}: {len(rep.fails)} failed, {len(rep.warns)} warnings, "
          f"{time.monotonic() - t0:.1f} s")
    for f in rep.fails:
        print(f"  FAIL {f}")
    for w in rep.warns:
        print(f"  warn {w}")
    sys.exit(1 if rep.fails else 0)


if __name__ == "__main__":
    main()
