#!/usr/bin/env python3
"""Checks the deployment files without docker or kubectl: every YAML file
parses; the compose services, Kubernetes objects and probes are the ones
deploy/README.md describes (the coordinator's probes: gRPC health, or, when
it serves TLS, which the kubelet's gRPC probe cannot speak, TCP or exec);
every `tessera` command line in them (compose, Kubernetes args, Dockerfile
CMD, systemd ExecStart, continued lines joined) names a subcommand and flags
that `tessera SUBCOMMAND --help` lists; and, where systemd-analyze exists,
the systemd units verify.

Usage: deploy/check.py PATH/TO/tessera   (exit 0: all good; 1: problems, listed)
"""
import json
import pathlib
import re
import shlex
import shutil
import subprocess
import sys
import tempfile

import yaml

DEPLOY = pathlib.Path(__file__).resolve().parent
tessera = sys.argv[1]
problems = []


def problem(where, what):
    problems.append(f"{where}: {what}")


def check_command(where, argv):
    """argv: the arguments after `tessera`."""
    if not argv:
        return problem(where, "empty tessera command")
    sub, flags = argv[0], [a.split("=")[0] for a in argv[1:] if a.startswith("--")]
    help_out = subprocess.run([tessera, sub, "--help"], capture_output=True, text=True)
    if help_out.returncode != 0:
        return problem(where, f"`tessera {sub}` is not a subcommand: {help_out.stderr.strip()}")
    listed = set(re.findall(r"--[a-z][a-z0-9-]*", help_out.stdout))
    for f in flags:
        if f not in listed:
            problem(where, f"`tessera {sub}` has no flag {f}")


docs = {}
for path in sorted(DEPLOY.rglob("*.yaml")):
    try:
        docs[path] = [d for d in yaml.safe_load_all(path.read_text()) if d is not None]
    except yaml.YAMLError as e:
        problem(path.name, f"invalid YAML: {e}")

compose = docs.get(DEPLOY / "compose.yaml", [{}])[0]
services = compose.get("services", {})
for name in ["coordinator", "worker"]:
    if name not in services:
        problem("compose.yaml", f"no service {name}")
for name, svc in services.items():
    if "command" in svc:
        check_command(f"compose.yaml service {name}", svc["command"])

k8s = [d for p, ds in docs.items() if p.parent.name == "k8s" for d in ds]
kinds = {(d.get("kind"), d.get("metadata", {}).get("name")) for d in k8s}
for kind in ["Service", "Deployment"]:
    if not any(k == kind for k, _ in kinds):
        problem("k8s", f"no {kind}")
# The coordinator's --data needs a persistent volume.
if not any(k == "PersistentVolumeClaim" for k, _ in kinds) and not any(
    d.get("kind") == "StatefulSet" and d.get("spec", {}).get("volumeClaimTemplates") for d in k8s
):
    problem("k8s", "no persistent volume for the coordinator (PersistentVolumeClaim or StatefulSet volumeClaimTemplates)")
for d in k8s:
    spec = d.get("spec", {}).get("template", {}).get("spec", {})
    for c in spec.get("containers", []):
        where = f"k8s {d['kind']} {d['metadata']['name']} container {c['name']}"
        check_command(where, c.get("args", []))
        if "coordinator" in c.get("args", [])[:1]:
            tls = "--tls-cert" in c["args"]
            for probe in ["livenessProbe", "readinessProbe"]:
                p = c.get(probe, {})
                if tls and ("grpc" in p or not ("tcpSocket" in p or "exec" in p)):
                    problem(where, f"{probe} is not a TCP or exec probe (the kubelet's gRPC probe has no TLS)")
                elif not tls and "grpc" not in p:
                    problem(where, f"{probe} is not a gRPC health probe")
kustomization = docs.get(DEPLOY / "k8s" / "kustomization.yaml", [{}])[0]
for r in kustomization.get("resources", []):
    if not (DEPLOY / "k8s" / r).is_file():
        problem("k8s/kustomization.yaml", f"resource {r} does not exist")

dockerfile = (DEPLOY / "Dockerfile").read_text()
entry = re.search(r"^ENTRYPOINT (\[.*\])$", dockerfile, re.M)
cmd = re.search(r"^CMD (\[.*\])$", dockerfile, re.M)
if not entry or json.loads(entry.group(1)) != ["tessera"]:
    problem("Dockerfile", 'ENTRYPOINT is not ["tessera"]')
if cmd:
    check_command("Dockerfile CMD", json.loads(cmd.group(1)))
else:
    problem("Dockerfile", "no CMD")

# The build image's Rust must be at least the workspace's rust-version.
cargo = (DEPLOY.parent / "Cargo.toml").read_text()
need = re.search(r'^rust-version\s*=\s*"([\d.]+)"', cargo, re.M)
have = re.search(r"^FROM rust:([\d.]+)", dockerfile, re.M)
version = lambda v: tuple(int(x) for x in v.split("."))
if need and (not have or version(have.group(1)) < version(need.group(1))):
    problem("Dockerfile", f"the build image's Rust is older than rust-version {need.group(1)}")

units = sorted((DEPLOY / "systemd").glob("*.service"))
for unit in units:
    # A backslash at a line's end continues it (as systemd reads it).
    m = re.search(r"^ExecStart=(\S+) (.*)$", re.sub(r"\\\n[ \t]*", " ", unit.read_text()), re.M)
    if not m or not m.group(1).endswith("/tessera"):
        problem(unit.name, "ExecStart does not run tessera")
        continue
    check_command(unit.name, shlex.split(m.group(2)))

analyze = shutil.which("systemd-analyze")
if analyze:
    # Verify copies whose ExecStart points at the binary under test (the
    # real path, /usr/local/bin/tessera, need not exist here).
    with tempfile.TemporaryDirectory() as tmp:
        for unit in units:
            text = re.sub(r"^ExecStart=\S+", f"ExecStart={pathlib.Path(tessera).resolve()}", unit.read_text(), flags=re.M)
            name = unit.name.replace("@.service", "@1.service")
            (pathlib.Path(tmp) / name).write_text(text)
            if name != unit.name:
                (pathlib.Path(tmp) / unit.name).write_text(text)
        names = [str(pathlib.Path(tmp) / u.name.replace("@.service", "@1.service")) for u in units]
        out = subprocess.run([analyze, "verify", *names], capture_output=True, text=True)
        if out.returncode != 0:
            problem("systemd", "systemd-analyze verify: " + (out.stdout + out.stderr).strip())
else:
    print("systemd-analyze not found: systemd units only checked for their command lines")

# The dashboard and the autoscaler read only the metric names that
# docs/operations.md lists as the contract (coordinator/src/metrics.rs).
CONTRACT = {"tessera_jobs", "tessera_units", "tessera_workers", "tessera_results_total",
            "tessera_lease_seconds", "tessera_samples_total", "tessera_store_healthy",
            "tessera_store_commit_seconds", "tessera_asset_bytes"}


def check_metrics(where, expr):
    for name in re.findall(r"\btessera_[a-z_]+", expr):
        base = re.sub(r"_(bucket|count|sum)$", "", name)
        if name not in CONTRACT and base not in CONTRACT:
            problem(where, f"{name} is not a metric the coordinator serves")


dashboards = sorted((DEPLOY / "grafana").glob("*.json"))
for path in dashboards:
    try:
        dash = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        problem(path.name, f"invalid JSON: {e}")
        continue
    for panel in dash.get("panels", []):
        for t in panel.get("targets", []):
            check_metrics(f"{path.name} panel {panel.get('title')!r}", t.get("expr", ""))
if not dashboards:
    problem("grafana", "no dashboard")
keda = [d for p, ds in docs.items() if p.parent.name == "keda" for d in ds]
if not any(d.get("kind") == "ScaledObject" for d in keda):
    problem("keda", "no ScaledObject")
for d in keda:
    for t in d.get("spec", {}).get("triggers", []):
        check_metrics(f"keda {d['metadata']['name']}", t.get("metadata", {}).get("query", ""))

for p in problems:
    print(p)
print(f"deploy check: {len(problems)} problem(s) in {len(docs)} YAML files, {len(units)} systemd units, the Dockerfile")
sys.exit(1 if problems else 0)
