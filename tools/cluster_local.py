#!/usr/bin/env python3
"""A placedb cluster on this machine (issue 18; docs/cluster.md): N hosts, each running a
nats-server (JetStream, file store, clustered), an etcd member, a `placedb-server --role shard`
and a `placedb-server --role worker`.

As root each host is a network namespace of its own on a bridge (10.<x>.0.<i+1>/24, the bridge
10.<x>.0.254 in the root namespace, so this machine reaches every host), as the tests' hosts
(tests/cluster/hosts.h); otherwise (or with --no-netns) each host is one loopback address
127.0.0.<i+2>. `status` says which.

  cluster_local.py up --hosts 3 [--dir var/cluster-local] [--roles shard,worker | none]
  cluster_local.py status [--json]
  cluster_local.py kill-host N     # SIGKILL every process of host N (netns: and cut its link)
  cluster_local.py start-host N    # link up, start its processes again on the same data
  cluster_local.py down [--purge]  # kill everything, remove namespaces/bridge (--purge: data too)

The state file (<dir>/state.json) names every address, port, pid, log and command line. The
processes outlive this command (their own sessions); `down` ends them. Python 3 stdlib only.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

# Ports are the same on every host: each host has an address (and, in netns mode, a port space)
# of its own.
PORTS = {
    "nats": 4222,
    "nats_cluster": 6222,
    "nats_monitor": 8222,
    "etcd_client": 2379,
    "etcd_peer": 2380,
    "shard_internal": 50061,
    "shard_listen": 50052,   # the shard's public listener (unused by clients; kept off 50051)
    "shard_metrics": 9474,
    "worker_listen": 50051,
    "worker_metrics": 9464,
}
REGISTRY = os.environ.get("PLACEDB_HOSTS_REGISTRY", "/run/placedb-hosts")
SUBNETS = range(250, 255)  # 10.250..254: the tests' hosts use 10.200..249
ENGINES = ("nats", "etcd")
ROLES = ("shard", "worker")


def find_binary(env: str, candidates: list[str]) -> str:
    if os.environ.get(env):
        return os.environ[env]
    for candidate in candidates:
        if os.access(candidate, os.X_OK):
            return candidate
    return candidates[0]


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(["ip", *args], capture_output=True, text=True)
    if check and result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")
    return result


def accepts(host: str, port: int, timeout: float = 0.5) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# ---- hosts ---------------------------------------------------------------------------------


def used_ten_subnets() -> set[int]:
    out = ip("-o", "-4", "addr", "show", check=False).stdout
    used = set()
    for word in out.split():
        if word.startswith("10.") and word.count(".") == 3:
            used.add(int(word.split(".")[1]))
    return used


def create_netns_hosts(count: int) -> dict:
    os.makedirs(REGISTRY, exist_ok=True)
    used = used_ten_subnets()
    for x in SUBNETS:
        if x in used:
            continue
        entry = f"{REGISTRY}/10.{x}"
        try:
            fd = os.open(entry, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            continue
        bridge = f"pdbc{x}b"
        names = [f"pdbc{x}h{i}" for i in range(count)]
        # Owner 0: a launcher's hosts, which outlive the launcher; only `down` removes them
        # (tests/cluster/cleanup_engines.sh and Hosts::Create leave owner-0 entries alone).
        with os.fdopen(fd, "w") as f:
            f.write("0\n" + bridge + "\n" + "".join(n + "\n" for n in names))
        prefix = f"10.{x}.0."
        hosts = {"kind": "netns", "subnet": x, "bridge": bridge, "registry": entry, "hosts": []}
        try:
            ip("link", "add", bridge, "type", "bridge")
            ip("addr", "add", prefix + "254/24", "dev", bridge)
            ip("link", "set", bridge, "up")
            for i, name in enumerate(names):
                veth = f"pdbc{x}v{i}"
                address = prefix + str(i + 1)
                ip("netns", "add", name)
                ip("link", "add", veth, "type", "veth", "peer", "name", veth + "i")
                ip("link", "set", veth + "i", "netns", name)
                ip("-n", name, "link", "set", veth + "i", "name", "eth0")
                ip("-n", name, "addr", "add", address + "/24", "dev", "eth0")
                ip("-n", name, "link", "set", "eth0", "up")
                ip("-n", name, "link", "set", "lo", "up")
                ip("link", "set", veth, "master", bridge)
                ip("link", "set", veth, "up")
                hosts["hosts"].append({"address": address, "netns": name, "veth": veth, "up": True})
        except Exception:
            remove_hosts(hosts | {"hosts": [{"netns": n, "veth": ""} for n in names]})
            raise
        return hosts
    raise RuntimeError("no free 10.x.0.0/24 subnet among 10.250..254")


def loopback_hosts(count: int) -> dict:
    return {"kind": "loopback",
            "hosts": [{"address": f"127.0.0.{i + 2}", "netns": "", "up": True}
                      for i in range(count)]}


def remove_hosts(hosts: dict) -> None:
    if hosts.get("kind") != "netns":
        return
    for host in hosts["hosts"]:
        if host.get("netns"):
            kill_namespace(host["netns"])
            ip("netns", "del", host["netns"], check=False)
        if host.get("veth"):
            # Usually gone with the namespace; a namespace is destroyed asynchronously.
            ip("link", "del", host["veth"], check=False)
    if hosts.get("bridge"):
        ip("link", "del", hosts["bridge"], check=False)
    if hosts.get("registry"):
        try:
            os.remove(hosts["registry"])
        except FileNotFoundError:
            pass


def kill_namespace(name: str) -> None:
    for _ in range(20):
        pids = ip("netns", "pids", name, check=False).stdout.split()
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(int(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.05)


# ---- processes -----------------------------------------------------------------------------


def commands(state: dict, i: int) -> dict[str, list[str]]:
    """Every process of host i: name -> argv (without the netns prefix)."""
    hosts = state["hosts"]["hosts"]
    me = hosts[i]["address"]
    d = f"{state['dir']}/h{i}"
    name = state["name"]
    nats_urls = ",".join(f"nats://{h['address']}:{PORTS['nats']}" for h in hosts)
    etcd_endpoints = ",".join(f"{h['address']}:{PORTS['etcd_client']}" for h in hosts)
    out = {}
    if "nats" in state["run"]:
        out["nats"] = [state["binaries"]["nats"], "-c", f"{d}/nats.conf"]
    if "etcd" in state["run"]:
        initial = ",".join(f"e{j}=http://{h['address']}:{PORTS['etcd_peer']}"
                           for j, h in enumerate(hosts))
        client = f"http://{me}:{PORTS['etcd_client']}"
        peer = f"http://{me}:{PORTS['etcd_peer']}"
        out["etcd"] = [state["binaries"]["etcd"], "--name", f"e{i}", "--data-dir", f"{d}/etcd",
                       "--listen-client-urls", client, "--advertise-client-urls", client,
                       "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
                       "--initial-cluster", initial, "--initial-cluster-state", "new",
                       "--initial-cluster-token", f"placedb-{name}", "--logger", "zap",
                       "--log-level", "warn"]
    common = [state["binaries"]["placedb"], "--cluster-name", name, "--nats", nats_urls,
              "--etcd", etcd_endpoints, "--console-listen", "off"]
    if state["hosts"]["kind"] == "netns":
        common.append("--allow-unauthenticated-remote")  # a local dev cluster: no tokens
    if "shard" in state["run"]:
        internal = f"{me}:{PORTS['shard_internal']}"
        out["shard"] = common + [
            "--role", "shard", "--shard-id", f"shard-{i}", "--advertise", internal,
            "--internal-listen", internal, "--listen", f"{me}:{PORTS['shard_listen']}",
            "--metrics-listen", f"{me}:{PORTS['shard_metrics']}", "--data-dir", f"{d}/shard",
        ] + state["server_args"]
    if "worker" in state["run"]:
        out["worker"] = common + [
            "--role", "worker", "--listen", f"{me}:{PORTS['worker_listen']}",
            "--metrics-listen", f"{me}:{PORTS['worker_metrics']}", "--data-dir", f"{d}/worker",
        ] + state["server_args"]
    return out


def ready_port(process: str) -> str:
    return {"nats": "nats", "etcd": "etcd_client", "shard": "shard_internal",
            "worker": "worker_listen"}[process]


def write_nats_config(state: dict, i: int) -> None:
    hosts = state["hosts"]["hosts"]
    me = hosts[i]["address"]
    d = f"{state['dir']}/h{i}"
    routes = "".join(f'    "nats-route://{h["address"]}:{PORTS["nats_cluster"]}"\n' for h in hosts)
    with open(f"{d}/nats.conf", "w") as f:
        f.write(f'server_name: n{i}\nlisten: "{me}:{PORTS["nats"]}"\n'
                f'http: "{me}:{PORTS["nats_monitor"]}"\n'
                f'jetstream {{\n  store_dir: "{d}/jetstream"\n  max_file_store: 8GB\n}}\n'
                f'cluster {{\n  name: placedb-{state["name"]}\n'
                f'  listen: "{me}:{PORTS["nats_cluster"]}"\n  routes: [\n{routes}  ]\n}}\n')


def start_host(state: dict, i: int, wait: float) -> list[str]:
    """Starts host i's processes; returns the ones not answering within `wait` seconds."""
    host = state["hosts"]["hosts"][i]
    if state["hosts"]["kind"] == "netns" and not host["up"]:
        ip("link", "set", host["veth"], "up")
    host["up"] = True
    d = f"{state['dir']}/h{i}"
    os.makedirs(d, exist_ok=True)
    write_nats_config(state, i)
    procs = state["processes"].setdefault(str(i), {})
    for name, argv in commands(state, i).items():
        if alive(procs.get(name, {}).get("pid", 0)):
            continue
        prefix = ["ip", "netns", "exec", host["netns"]] if host["netns"] else []
        log = f"{d}/{name}.log"
        with open(log, "ab") as out:
            # A session of its own: the process outlives this command and its group is killable.
            p = subprocess.Popen(prefix + argv, stdout=out, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, start_new_session=True)
        procs[name] = {"pid": p.pid, "log": log, "argv": prefix + argv,
                       "port": PORTS[ready_port(name)]}
    save(state)
    deadline = time.time() + wait
    missing = list(procs)
    while missing and time.time() < deadline:
        missing = [n for n in procs if not accepts(host["address"], procs[n]["port"])]
        if missing:
            time.sleep(0.2)
    return missing


def kill_host(state: dict, i: int) -> None:
    host = state["hosts"]["hosts"][i]
    if state["hosts"]["kind"] == "netns":
        if host["up"]:
            ip("link", "set", host["veth"], "down")
        kill_namespace(host["netns"])
    for proc in state["processes"].get(str(i), {}).values():
        for target in (-proc["pid"], proc["pid"]):
            try:
                os.kill(target, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    host["up"] = False
    save(state)


def meta_leader(state: dict) -> str:
    for host in state["hosts"]["hosts"]:
        if not host["up"]:
            continue
        url = f"http://{host['address']}:{PORTS['nats_monitor']}/jsz"
        try:
            with urllib.request.urlopen(url, timeout=1) as r:
                leader = json.load(r).get("meta_cluster", {}).get("leader", "")
                # A killed host's server stays the leader in the survivors' view until they
                # elect another: only a live host's counts.
                if leader.startswith("n") and leader[1:].isdigit() and \
                        int(leader[1:]) < len(state["hosts"]["hosts"]) and \
                        state["hosts"]["hosts"][int(leader[1:])]["up"]:
                    return leader
        except (OSError, ValueError):
            continue
    return ""


# ---- state ---------------------------------------------------------------------------------


def state_path(directory: str) -> str:
    return os.path.join(directory, "state.json")


def save(state: dict) -> None:
    tmp = state_path(state["dir"]) + ".tmp"
    with open(tmp, "w") as f:
        json.dump(state, f, indent=2)
    os.replace(tmp, state_path(state["dir"]))


def load(directory: str) -> dict:
    try:
        with open(state_path(directory)) as f:
            return json.load(f)
    except FileNotFoundError:
        sys.exit(f"cluster_local: no cluster in {directory} (run `up` first)")


def status(state: dict) -> dict:
    out = {"kind": state["hosts"]["kind"], "name": state["name"], "meta_leader": meta_leader(state),
           "nats": [f"nats://{h['address']}:{PORTS['nats']}" for h in state["hosts"]["hosts"]],
           "etcd": [f"{h['address']}:{PORTS['etcd_client']}" for h in state["hosts"]["hosts"]],
           "workers": [f"{h['address']}:{PORTS['worker_listen']}"
                       for h in state["hosts"]["hosts"]] if "worker" in state["run"] else [],
           "hosts": []}
    for i, host in enumerate(state["hosts"]["hosts"]):
        procs = {}
        for name, proc in state["processes"].get(str(i), {}).items():
            procs[name] = {"pid": proc["pid"], "alive": alive(proc["pid"]),
                           "answers": host["up"] and accepts(host["address"], proc["port"]),
                           "log": proc["log"]}
        out["hosts"].append({"host": i, "address": host["address"], "netns": host["netns"],
                             "up": host["up"], "processes": procs})
    return out


# ---- commands ------------------------------------------------------------------------------


def cmd_up(args) -> int:
    directory = os.path.abspath(args.dir)
    if os.path.exists(state_path(directory)):
        sys.exit(f"cluster_local: a cluster is already up in {directory} (`down` first)")
    os.makedirs(directory, exist_ok=True)
    run = list(ENGINES)
    if args.roles != "none":
        run += [r for r in args.roles.split(",") if r]
        bad = [r for r in run if r not in ENGINES + ROLES]
        if bad:
            sys.exit(f"cluster_local: unknown role(s) {bad}")
    use_netns = os.geteuid() == 0 and not args.no_netns and shutil.which("ip")
    hosts = create_netns_hosts(args.hosts) if use_netns else loopback_hosts(args.hosts)
    state = {
        "dir": directory, "name": args.name, "run": run, "hosts": hosts, "processes": {},
        "server_args": args.server_arg or [],
        "binaries": {
            "nats": find_binary("PLACEDB_NATS_SERVER", ["/usr/sbin/nats-server", "/usr/bin/nats-server"]),
            "etcd": find_binary("PLACEDB_ETCD", ["/usr/bin/etcd", "/usr/sbin/etcd"]),
            "placedb": os.path.abspath(args.placedb_server),
        },
    }
    save(state)
    print(f"cluster_local: {args.hosts} hosts ({hosts['kind']}): "
          + ", ".join(h["address"] for h in hosts["hosts"]))
    missing = {}
    for i in range(args.hosts):  # every host first: the members need each other
        missing[i] = start_host(state, i, 0)
    deadline = time.time() + args.wait
    for i in range(args.hosts):
        missing[i] = start_host(state, i, max(0.0, deadline - time.time()))
    for i, names in missing.items():
        for name in names:
            print(f"cluster_local: host {i} {name} not answering; see "
                  f"{state['processes'][str(i)][name]['log']}", file=sys.stderr)
    print(f"cluster_local: state in {state_path(directory)}")
    return 1 if any(missing.values()) else 0


def cmd_status(args) -> int:
    s = status(load(os.path.abspath(args.dir)))
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"hosts: {s['kind']}  meta leader: {s['meta_leader'] or '-'}")
    for h in s["hosts"]:
        procs = "  ".join(f"{n}={'up' if p['answers'] else ('running' if p['alive'] else 'down')}"
                          f"({p['pid']})" for n, p in h["processes"].items())
        print(f"host {h['host']} {h['address']} {'up' if h['up'] else 'KILLED'}  {procs}")
    return 0


def cmd_kill_host(args) -> int:
    state = load(os.path.abspath(args.dir))
    kill_host(state, args.host)
    print(f"cluster_local: host {args.host} killed")
    return 0


def cmd_start_host(args) -> int:
    state = load(os.path.abspath(args.dir))
    missing = start_host(state, args.host, args.wait)
    if missing:
        print(f"cluster_local: host {args.host}: {missing} not answering", file=sys.stderr)
        return 1
    print(f"cluster_local: host {args.host} started")
    return 0


def cmd_down(args) -> int:
    directory = os.path.abspath(args.dir)
    state = load(directory)
    for i in range(len(state["hosts"]["hosts"])):
        kill_host(state, i)
    remove_hosts(state["hosts"])
    os.remove(state_path(directory))
    if args.purge:
        shutil.rmtree(directory, ignore_errors=True)
    print("cluster_local: down" + (" (data removed)" if args.purge else f" (logs, data in {directory})"))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", default=os.environ.get("PLACEDB_CLUSTER_DIR", "var/cluster-local"),
                        help="state, logs and data (var/cluster-local)")
    sub = parser.add_subparsers(dest="command", required=True)
    up = sub.add_parser("up", help="start a cluster")
    up.add_argument("--hosts", type=int, default=3)
    up.add_argument("--name", default="placedb", help="cluster.name (etcd prefix, stream names)")
    up.add_argument("--roles", default="shard,worker",
                    help="placedb roles per host: shard,worker (default) or none (engines only)")
    up.add_argument("--placedb-server", default="build/server/placedb-server")
    up.add_argument("--server-arg", action="append",
                    help="extra placedb-server argument (repeatable), e.g. --server-arg=--config=x.yaml")
    up.add_argument("--no-netns", action="store_true", help="loopback addresses even as root")
    up.add_argument("--wait", type=float, default=60, help="seconds to wait for every process")
    up.set_defaults(func=cmd_up)
    st = sub.add_parser("status", help="hosts, processes, JetStream meta leader")
    st.add_argument("--json", action="store_true")
    st.set_defaults(func=cmd_status)
    kh = sub.add_parser("kill-host", help="SIGKILL every process of a host (and cut its link)")
    kh.add_argument("host", type=int)
    kh.set_defaults(func=cmd_kill_host)
    sh = sub.add_parser("start-host", help="start a killed host again")
    sh.add_argument("host", type=int)
    sh.add_argument("--wait", type=float, default=60)
    sh.set_defaults(func=cmd_start_host)
    dn = sub.add_parser("down", help="stop everything, remove the hosts")
    dn.add_argument("--purge", action="store_true", help="also remove data and logs")
    dn.set_defaults(func=cmd_down)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
