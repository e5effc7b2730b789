#!/usr/bin/python3
"""Cluster soak and worker throughput (issue 18; docs/cluster.md), on tools/cluster_local.py.

Soak (default): `up --hosts 3`, 2 maps, `--agents` agents x `--frames` frames through the
workers' public placedb.v1 API (the Python SDK, client/python), each agent at most
`--agent-rate` frames/s (default 7: 1,250 frames take ~180 s, past the 5th kill), a random host killed every
`--kill-every` s (`--kills` kills, each restarted after `--down` s), `--query-rate` queries/s
with a `--deadline` budget and at most one retry (on another worker, in the budget left). Then:
every acknowledged place is read back through the workers; then the 2-of-3-NATS-down check
(ingest refused UNAVAILABLE, nothing acknowledged, resumes once one returns). Prints
`name value unit` lines (bench/bench_output.h's format):

  acknowledged, lost (acknowledged ids missing from the map), duplicates ((agent, sequence)
  stored under more than one id, or one frame acknowledged with two ids), stall_kill<i> (longest
  time without any ack in the --kill-every s after kill i), stall_max, query_within_deadline
  (share), query_retries, nats_2down_refused / nats_2down_acknowledged / nats_2down_resume.

Compaction (issue 35, `--compact-after-records N`: the workers' cluster.compact_after_records,
compact_after_bytes 0): every `--sample-every` s the maps' streams' bytes (NATS' /jsz, the most a
live server stores of each), their first sequences and the snapshots stream's bytes (where the
bases are) go to `--stream-csv` (default: stream_bytes.csv in the cluster's directory); then
stream_bytes_max, stream_bytes_end, snapshots_stream_bytes_end, compactions (new bases seen in
etcd bases/), and after the read-back a replica of soak-a moved to the shard without one:
catchup_new_replica (s until it applied the stream's end) and what it restored from (its log).

Throughput (`--workers 1,2,3`): for each count, `--agents` agents ingest for `--duration` s
through that many workers: frames/s of precomputed features (`feat`) and, with `--images`, of
JPEG frames with detection (`jpeg`). `--worker-cpu C` caps each worker process at C cores (a
cgroup CPU quota, as root): every process of the 3 "hosts" shares this machine's cores, so
without a cap the machine, not the worker tier, is what saturates.

Replica (`replica --places N`): one map of N places (synthetic frames of `--features`
features), then moved by hand to the third shard (docs/cluster.md, "Move a map"): seconds from
the placement change until the new replica has applied the stream's last place (restored from a
live replica's checkpoint, then the tail), and the share of stored frames it answers with their
own place once the other replica's shard is SIGKILLed.

Frames: precomputed synthetic ORB features (deterministic per agent and sequence: a frame
resent after a failover is the same frame with the same message id `<agent>/<sequence>`), or
JPEG files (--images DIR). Each frame carries its sequence: a failover resends unacknowledged
frames and the workers' de-duplication must answer them with their original place id.

Needs the shard and worker roles (cluster mode): `self-test` checks this script's own parts
without them (frames, stall and query accounting, verification, the kill schedule on the engines).

  bench/cluster_soak.py [--sdk build/client/python] [--placedb-server build/server/placedb-server]
  bench/cluster_soak.py --workers 1,2,3 --images /work/shared/data/rtabmap-loop
  bench/cluster_soak.py self-test
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import unittest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAUNCHER = os.path.join(ROOT, "tools", "cluster_local.py")
MAPS = ("soak-a", "soak-b")


def out(name: str, value, unit: str) -> None:
    print(f"{name} {value:.6g} {unit}" if isinstance(value, float) else f"{name} {value} {unit}",
          flush=True)


# ---- launcher ------------------------------------------------------------------------------


class Cluster:
    """tools/cluster_local.py through its command line (its state file is the truth)."""

    def __init__(self, directory: str):
        self.directory = directory

    def run(self, *args: str, check: bool = True) -> str:
        r = subprocess.run([sys.executable, LAUNCHER, "--dir", self.directory, *args],
                           capture_output=True, text=True)
        if check and r.returncode != 0:
            raise RuntimeError(f"cluster_local {' '.join(args)}: {r.stdout}{r.stderr}")
        return r.stdout

    def status(self) -> dict:
        return json.loads(self.run("status", "--json"))

    def up(self, hosts: int, extra: list[str]) -> None:
        self.run("up", "--hosts", str(hosts), *extra)

    def kill_host(self, host: int) -> None:
        self.run("kill-host", str(host))

    def start_host(self, host: int) -> None:
        self.run("start-host", str(host))

    def kill_process(self, host: int, name: str) -> None:
        pid = self.status()["hosts"][host]["processes"][name]["pid"]
        try:
            os.kill(pid, 9)
        except ProcessLookupError:
            pass

    def down(self, purge: bool = False) -> None:
        """Stops everything; keeps the logs and data for a look unless `purge`."""
        self.run("down", *(["--purge"] if purge else []), check=False)
        if purge:
            shutil.rmtree(self.directory, ignore_errors=True)
        else:
            print(f"cluster_soak: logs and data in {self.directory}", file=sys.stderr)


# ---- frames --------------------------------------------------------------------------------


def synthetic_frame(sdk, agent: str, sequence: int, features: int = 500):
    """Deterministic ORB-like features of (agent, sequence): the same frame when resent."""
    import numpy as np

    rng = np.random.default_rng(_seed(agent, sequence))
    keypoints = np.zeros((features, 6), dtype=np.float32)
    keypoints[:, 0] = rng.uniform(0, 639, features)
    keypoints[:, 1] = rng.uniform(0, 479, features)
    keypoints[:, 2] = 31.0
    keypoints[:, 3] = rng.uniform(0, 360, features)
    keypoints[:, 4] = rng.uniform(0, 1, features)
    descriptors = rng.integers(0, 256, (features, 32), dtype=np.uint8)
    return sdk.Frame(keypoints=keypoints, descriptors=descriptors, image_size=(640, 480),
                     sequence=sequence)


def _seed(agent: str, sequence: int) -> int:
    # hash() of a str differs per process: a stable seed instead.
    value = sequence * 1000003
    for byte in agent.encode():
        value = (value * 131 + byte) % (1 << 61)
    return value


def image_frame(sdk, paths: list[str], sequence: int):
    with open(paths[sequence % len(paths)], "rb") as f:
        return sdk.Frame(image=f.read(), sequence=sequence)


# ---- accounting (pure: self-tested) --------------------------------------------------------


class Acks:
    """Every acknowledgement: (agent, sequence) -> place ids (more than one: a duplicate)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.by_frame: dict[tuple[str, int], set[int]] = {}
        self.maps: dict[tuple[str, int], str] = {}
        self.times: list[float] = []
        self.agent_times: dict[str, list[float]] = {}

    def add(self, map_name: str, agent: str, sequence: int, place_id: int, at: float) -> None:
        with self.lock:
            self.by_frame.setdefault((agent, sequence), set()).add(place_id)
            self.maps[(agent, sequence)] = map_name
            self.times.append(at)
            self.agent_times.setdefault(agent, []).append(at)

    def count(self) -> int:
        with self.lock:
            return len(self.by_frame)


def stalls(ack_times: list[float], kills: list[float], window: float,
           finished: float = float("inf")) -> list:
    """Per kill at time k: the longest gap without an ack within [k, min(k + window, finished)]
    (gaps that start before k count from k; an empty window counts whole); None for a kill at
    or after `finished` (every frame acknowledged: nothing left to stall)."""
    times = sorted(ack_times)
    result = []
    for k in kills:
        if k >= finished:
            result.append(None)
            continue
        end = min(k + window, finished)
        inside = [t for t in times if k <= t <= end]
        edges = [k] + inside + [min(end, max(times[-1], k) if times else end)]
        if not inside:
            edges = [k, end]
        result.append(max(b - a for a, b in zip(edges, edges[1:])))
    return result


def agent_stalls(acks: Acks, frames: int, kills: list[float], window: float) -> list:
    """Per kill: the longest stall of any agent (stalls() over that agent's own acks, up to its
    last ack once it has all `frames`): the agents of the killed worker are the ones that wait.
    None when every agent had finished before the kill."""
    per_agent = []
    for agent, times in acks.agent_times.items():
        done = sum(1 for (a, _) in acks.by_frame if a == agent) >= frames
        per_agent.append(stalls(times, kills, window, max(times) if done else float("inf")))
    result = []
    for i in range(len(kills)):
        values = [s[i] for s in per_agent if s[i] is not None]
        result.append(max(values) if values else None)
    return result


def verify(acks: Acks, stored: dict[str, list[tuple[int, str, int]]]) -> tuple[int, int]:
    """(lost, duplicates) of acknowledged frames against the stored places of each map
    ((place id, agent, sequence) triples)."""
    present: dict[str, set[int]] = {m: {p for p, _, _ in places} for m, places in stored.items()}
    lost = 0
    duplicates = 0
    for frame, ids in acks.by_frame.items():
        duplicates += len(ids) - 1
        lost += sum(1 for i in ids if i not in present.get(acks.maps[frame], set()))
    for places in stored.values():
        seen: dict[tuple[str, int], int] = {}
        for _, agent, sequence in places:
            seen[(agent, sequence)] = seen.get((agent, sequence), 0) + 1
        duplicates += sum(n - 1 for n in seen.values())
    return lost, duplicates


class Queries:
    def __init__(self):
        self.lock = threading.Lock()
        self.total = self.within = self.retries = 0

    def add(self, within: bool, retried: bool) -> None:
        with self.lock:
            self.total += 1
            self.within += int(within)
            self.retries += int(retried)


def query_once_with_retry(attempts, deadline: float) -> tuple[bool, bool]:
    """`attempts`: up to two callables taking a timeout (s); the second only when the first
    fails, with what is left of `deadline`. Returns (answered within deadline, retried)."""
    start = time.monotonic()
    for i, attempt in enumerate(attempts[:2]):
        left = deadline - (time.monotonic() - start)
        if left <= 0:
            return False, i > 0
        try:
            attempt(left)
            return time.monotonic() - start <= deadline, i > 0
        except Exception:  # noqa: BLE001 -- any failure is a miss; the retry decides
            continue
    return False, True


# ---- the soak ------------------------------------------------------------------------------


def map_settings(sdk, precomputed: bool):
    # Precomputed features carry no pixels: boxes can only come from the agent (none here).
    return sdk.MapSettings(box_source="agent") if precomputed else None


def workers_of(status: dict, live_only: bool = True) -> list[str]:
    return [w for w, h in zip(status["workers"], status["hosts"]) if h["up"] or not live_only]


def agent_loop(sdk, cluster: Cluster, map_name: str, agent: str, frames: int, make_frame,
               acks: Acks, stop: threading.Event, worker_pick) -> None:
    """Ingests sequences 0..frames-1; on any stream failure reconnects to another worker and
    resends from the first unacknowledged sequence (same message ids)."""
    next_sequence = 0
    failures = 0
    while next_sequence < frames and not stop.is_set():
        address = worker_pick(failures)
        try:
            with sdk.Client(address) as client:
                stream = client.ingest(map_name, (make_frame(agent, s)
                                                  for s in range(next_sequence, frames)),
                                       agent_id=agent, max_in_flight=4)
                for result in stream:
                    if result.error:
                        raise RuntimeError(result.error)
                    if result.stored or result.place_id:
                        acks.add(map_name, agent, result.sequence, result.place_id,
                                 time.monotonic())
                    next_sequence = result.sequence + 1
                    if stop.is_set():
                        break
        except Exception as e:  # noqa: BLE001 -- a failover: next worker, resend the rest
            failures += 1
            if failures in (1, 10, 100):
                print(f"cluster_soak: {agent}: failure {failures}: {type(e).__name__}: {e}",
                      file=sys.stderr)
            time.sleep(0.2)


def soak(args, sdk) -> int:
    cluster = Cluster(tempfile.mkdtemp(prefix="placedb-soak-"))
    compaction = [] if args.compact_after_records is None else [
        f"--server-arg=--compact-after-records={args.compact_after_records}",
        "--server-arg=--compact-after-bytes=0"]
    cluster.up(3, ["--placedb-server", args.placedb_server, "--roles", args.roles]
               + [f"--server-arg={a}" for a in args.server_arg or []] + compaction)
    try:
        status = cluster.status()
        with sdk.Client(status["workers"][0]) as client:
            for m in MAPS:
                client.create_map(m, map_settings(sdk, not args.image_paths))
        acks, queries = Acks(), Queries()
        stop = threading.Event()
        rng = random.Random(args.seed)
        lock = threading.Lock()
        live = {"workers": workers_of(status)}

        def pick(failures: int) -> str:
            with lock:
                w = live["workers"]
                return w[failures % len(w)]

        unpaced = (lambda a, s: image_frame(sdk, args.image_paths, s)) if args.image_paths else \
            (lambda a, s: synthetic_frame(sdk, a, s))
        # Agents send at most --agent-rate frames/s each (a robot's keyframe rate), on a schedule
        # from the soak's start: the ingest then spans the kills instead of ending before them,
        # and an agent that lost time to a failover catches up at once.
        started = time.monotonic()

        def make(agent: str, sequence: int):
            if args.agent_rate > 0:
                due = started + sequence / args.agent_rate
                while not stop.is_set() and time.monotonic() < due:
                    time.sleep(min(0.05, due - time.monotonic()))
            return unpaced(agent, sequence)
        threads = [threading.Thread(target=agent_loop, daemon=True, args=(
            sdk, cluster, MAPS[i % 2], f"agent-{i}", args.frames, make, acks, stop, pick))
            for i in range(args.agents)]

        def query_loop() -> None:
            period = 1.0 / args.query_rate
            next_at = time.monotonic()
            clients = {w: sdk.Client(w) for w in status["workers"]}
            while not stop.is_set():
                next_at += period
                with lock:
                    ws = list(live["workers"])
                first = rng.randrange(len(ws))
                frame = synthetic_frame(sdk, "query", rng.randrange(1 << 20))
                m = MAPS[rng.randrange(2)]
                attempts = [lambda t, w=ws[(first + k) % len(ws)]:
                            clients[w].query(m, frame, top_k=5, timeout=t) for k in range(2)]
                within, retried = query_once_with_retry(attempts, args.deadline)
                queries.add(within, retried)
                time.sleep(max(0.0, next_at - time.monotonic()))
            for c in clients.values():
                c.close()

        hosts_up = [True] * 3
        csv_path = args.stream_csv or os.path.join(cluster.directory, "stream_bytes.csv")
        sampler = StreamSampler(status, csv_path, args.sample_every, hosts_up, lock)
        sampler.thread.start()
        for t in threads:
            t.start()
        qt = threading.Thread(target=query_loop, daemon=True)
        qt.start()
        kills = []
        for i in range(args.kills):
            time.sleep(args.kill_every - args.down)
            host = rng.randrange(3)
            with lock:
                live["workers"] = [w for j, w in enumerate(status["workers"]) if j != host]
            with lock:
                hosts_up[host] = False
            cluster.kill_host(host)
            kills.append(time.monotonic())
            out(f"kill{i}_host", host, "host")
            time.sleep(args.down)
            cluster.start_host(host)
            with lock:
                live["workers"] = list(status["workers"])
                hosts_up[host] = True
        for t in threads:
            t.join(timeout=args.finish_timeout)
        stop.set()
        qt.join()

        out("acknowledged", acks.count(), "frames")
        stored = {}
        try:
            with sdk.Client(status["workers"][0]) as client:
                for m in MAPS:
                    stored[m] = [(p.place_id, p.agent_id, p.sequence)
                                 for p in client.iter_places(m, limit=1000, timeout=60)]
            lost, duplicates = verify(acks, stored)
            out("lost", lost, "places")
            out("duplicates", duplicates, "places")
            if args.compact_after_records is not None:
                # A new replica now: from the base (or a live replica's newer checkpoint) + tail.
                last = max(p for p, _, _ in stored[MAPS[0]])
                took, restored, _, _ = move_replica(status, MAPS[0], last)
                out("catchup_new_replica", took, "s")
                print(f"cluster_soak: {restored}", file=sys.stderr)
        except sdk.Error as e:  # e.g. no shard role running: nothing to read back from
            print(f"cluster_soak: cannot read the maps back: {type(e).__name__}: {e}",
                  file=sys.stderr)
        # Without the read-back: one frame acknowledged under two ids is still a duplicate.
        out("ack_duplicates", sum(len(i) - 1 for i in acks.by_frame.values()), "frames")
        complete = acks.count() == args.agents * args.frames
        out("ingest_complete", int(complete), "bool")
        per_kill = agent_stalls(acks, args.frames, kills, args.kill_every)
        for i, s in enumerate(per_kill):
            if s is None:
                print(f"cluster_soak: kill {i} came after the last ack: no stall to measure",
                      file=sys.stderr)
            else:
                out(f"stall_kill{i}", s, "s")
        measured = [s for s in per_kill if s is not None]
        if measured:
            out("stall_max", max(measured), "s")
        sampler.stop.set()
        sampler.thread.join()
        out("stream_bytes_max", sampler.max_bytes, "bytes")
        out("stream_bytes_end", sampler.last_bytes, "bytes")
        out("snapshots_stream_bytes_end", sampler.snapshots_bytes, "bytes")
        out("compactions", sampler.compactions, "bases")
        svg_path = os.path.splitext(csv_path)[0] + ".svg"
        plot_stream_csv(csv_path, svg_path, [k - started for k in kills])
        print(f"cluster_soak: stream bytes over time in {csv_path} (plot: {svg_path})",
              file=sys.stderr)
        out("queries", queries.total, "queries")
        out("query_within_deadline", queries.within / max(1, queries.total), "share")
        out("query_retries", queries.retries, "queries")
        nats_two_down(cluster, sdk, status)
    finally:
        cluster.down()
    return 0


def nats_two_down(cluster: Cluster, sdk, status: dict) -> None:
    """Two of three nats-servers SIGKILLed: a new frame is refused (UNAVAILABLE), nothing is
    acknowledged; one returns: the same frame is acknowledged (bounded wait)."""
    for host in (1, 2):
        cluster.kill_process(host, "nats")
    worker = status["workers"][0]
    frame = synthetic_frame(sdk, "nats-check", 0)
    refused = acknowledged = 0
    with sdk.Client(worker) as client:
        try:
            for r in client.ingest(MAPS[0], [frame], agent_id="nats-check", timeout=30):
                if r.error:
                    refused += int(isinstance(r.error, sdk.Unavailable) or
                                   "UNAVAILABLE" in str(r.error).upper())
                    print(f"nats_2down: refused: {r.error}", file=sys.stderr)
                elif r.stored or r.place_id:
                    acknowledged += 1
        except sdk.Unavailable:
            refused += 1
        except sdk.Error as e:
            print(f"nats_2down: {type(e).__name__}: {e}", file=sys.stderr)
        out("nats_2down_refused", refused, "frames")
        out("nats_2down_acknowledged", acknowledged, "frames")
        cluster.start_host(1)  # starts only its missing process: nats
        start = time.monotonic()
        resumed = False
        while not resumed and time.monotonic() - start < 60:
            try:
                for r in client.ingest(MAPS[0], [frame], agent_id="nats-check", timeout=10):
                    resumed = not r.error and (r.stored or bool(r.place_id))
            except sdk.Error:
                time.sleep(0.5)
        out("nats_2down_resume", time.monotonic() - start if resumed else -1.0, "s")
    cluster.start_host(2)


def cap_cpu(pid: int, name: str, cores: float) -> str:
    """Puts process `pid` (all its threads) in a new cgroup limited to `cores` CPUs (the cpu
    controller's quota: cgroup v2 cpu.max, else v1 cpu.cfs_quota_us). Returns the cgroup's
    directory, for remove_cgroup."""
    period = 100000
    quota = str(int(cores * period))
    v2 = os.path.exists("/sys/fs/cgroup/cgroup.controllers")
    directory = f"/sys/fs/cgroup/{name}" if v2 else f"/sys/fs/cgroup/cpu/{name}"
    os.makedirs(directory, exist_ok=True)
    if v2:
        with open(f"{directory}/cpu.max", "w") as f:
            f.write(f"{quota} {period}")
    else:
        with open(f"{directory}/cpu.cfs_period_us", "w") as f:
            f.write(str(period))
        with open(f"{directory}/cpu.cfs_quota_us", "w") as f:
            f.write(quota)
    with open(f"{directory}/cgroup.procs", "w") as f:
        f.write(str(pid))
    return directory


def remove_cgroup(directory: str) -> None:
    """Removes a cgroup of cap_cpu once its processes are gone (a few tries: exits take a moment)."""
    for _ in range(50):
        try:
            os.rmdir(directory)
            return
        except FileNotFoundError:
            return
        except OSError:
            time.sleep(0.1)
    print(f"cluster_soak: could not remove {directory}", file=sys.stderr)


def throughput(args, sdk) -> int:
    counts = [int(c) for c in args.workers.split(",")]
    cluster = Cluster(tempfile.mkdtemp(prefix="placedb-throughput-"))
    cluster.up(max(3, max(counts)), ["--placedb-server", args.placedb_server, "--roles", args.roles]
               + [f"--server-arg={a}" for a in args.server_arg or []])
    cgroups = []
    try:
        status = cluster.status()
        if args.worker_cpu:
            # Each worker stands in for a machine of its own with this many cores: the worker
            # tier is then the bottleneck, as on a fleet's cluster, not the 2 cores all the
            # "hosts" here share.
            for i, host in enumerate(status["hosts"]):
                cgroups.append(cap_cpu(host["processes"]["worker"]["pid"],
                                       f"placedb-bench-worker{i}", args.worker_cpu))
            out("throughput_worker_cpu_cap", args.worker_cpu, "cores")
        modes = [("feat", lambda a, s: synthetic_frame(sdk, a, s))]
        if args.image_paths:
            modes.append(("jpeg", lambda a, s: image_frame(sdk, args.image_paths, s)))
        with sdk.Client(status["workers"][0]) as client:
            for mode, _ in modes:
                for n in counts:
                    client.create_map(f"tp-{mode}-{n}", map_settings(sdk, mode == "feat"))
        for mode, make in modes:
            for n in counts:
                acks, stop = Acks(), threading.Event()
                ws = status["workers"][:n]
                threads = [threading.Thread(target=agent_loop, daemon=True, args=(
                    sdk, cluster, f"tp-{mode}-{n}", f"agent-{i}", 1 << 30, make, acks, stop,
                    lambda f, i=i: ws[(i + f) % n])) for i in range(args.agents)]
                start = time.monotonic()
                for t in threads:
                    t.start()
                time.sleep(args.duration)
                stop.set()
                elapsed = time.monotonic() - start
                for t in threads:
                    t.join(timeout=30)
                out(f"throughput_{mode}_workers{n}", acks.count() / elapsed, "frames/s")
    finally:
        cluster.down()
        for directory in cgroups:
            remove_cgroup(directory)
    return 0


# ---- a new replica of a large map ----------------------------------------------------------


def etcd_prefix(status: dict, key: str) -> dict[str, str]:
    """Keys under `key` (etcdctl get --prefix) -> values; every value here is one line."""
    r = subprocess.run(["etcdctl", "--endpoints", ",".join(status["etcd"]), "get", "--prefix", key],
                       capture_output=True, text=True, env={**os.environ, "ETCDCTL_API": "3"},
                       timeout=30)
    if r.returncode != 0:
        raise RuntimeError(f"etcdctl get {key}: {r.stderr}")
    lines = r.stdout.splitlines()
    return dict(zip(lines[0::2], lines[1::2]))


def etcd_put(status: dict, key: str, value: str) -> None:
    subprocess.run(["etcdctl", "--endpoints", ",".join(status["etcd"]), "put", key, value],
                   check=True, capture_output=True, env={**os.environ, "ETCDCTL_API": "3"},
                   timeout=30)


def applied_of(status: dict, map_name: str) -> dict[str, int]:
    prefix = f"/placedb/{status['name']}/applied/{map_name}/"
    return {k[len(prefix):]: int(v) for k, v in etcd_prefix(status, prefix).items()}


def stream_sample(status: dict, up: list[bool]) -> dict[str, dict]:
    """The cluster's streams as the live NATS servers store them (/jsz): stream name -> the
    largest bytes / messages / first_seq any live server reports."""
    import urllib.request
    streams: dict[str, dict] = {}
    for host, alive in zip(status["hosts"], up):
        if not alive:
            continue
        url = f"http://{host['address']}:8222/jsz?streams=true"
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                jsz = json.load(r)
        except OSError:
            continue
        for account in jsz.get("account_details", []):
            for detail in account.get("stream_detail", []):
                state = detail.get("state", {})
                seen = streams.setdefault(detail["name"], {"bytes": 0, "messages": 0,
                                                           "first_seq": 0})
                seen["bytes"] = max(seen["bytes"], state.get("bytes", 0))
                seen["messages"] = max(seen["messages"], state.get("messages", 0))
                seen["first_seq"] = max(seen["first_seq"], state.get("first_seq", 0))
    return streams


def bases_of(status: dict) -> dict[str, int]:
    """etcd bases/<map> -> the base sequence (compaction)."""
    prefix = f"/placedb/{status['name']}/bases/"
    out_ = {}
    for key, value in etcd_prefix(status, prefix).items():
        try:
            out_[key[len(prefix):]] = int(json.loads(value)["manifest"]["base"])
        except (ValueError, KeyError):
            pass
    return out_


class StreamSampler:
    """Samples the streams every `every` s into a CSV: t, map streams' bytes (sum), snapshots
    stream's bytes, then per map stream bytes, messages, first_seq; counts new bases."""

    def __init__(self, status: dict, path: str, every: float, up: list[bool], lock):
        self.status, self.path, self.every, self.up, self.lock = status, path, every, up, lock
        self.stop = threading.Event()
        self.max_bytes = 0
        self.last_bytes = 0
        self.snapshots_bytes = 0
        self.bases: dict[str, int] = {}
        self.compactions = 0
        self.thread = threading.Thread(target=self.run, daemon=True)

    def sample(self, t: float, f) -> None:
        with self.lock:
            up = list(self.up)
        streams = stream_sample(self.status, up)
        prefix = f"PLACEDB_{self.status['name'].upper()}_"
        snapshots = streams.pop(prefix + "SNAPSHOTS", {}).get("bytes", 0)
        maps = {n: v for n, v in sorted(streams.items()) if n.startswith(prefix)}
        total = sum(v["bytes"] for v in maps.values())
        self.max_bytes = max(self.max_bytes, total)
        self.last_bytes, self.snapshots_bytes = total, snapshots
        cells = [f"{t:.1f}", str(total), str(snapshots)]
        for name, v in maps.items():
            cells += [name, str(v["bytes"]), str(v["messages"]), str(v["first_seq"])]
        f.write(",".join(cells) + "\n")
        f.flush()
        try:
            for m, base in bases_of(self.status).items():
                if self.bases.get(m) != base:
                    self.compactions += 1
                    self.bases[m] = base
        except (RuntimeError, subprocess.TimeoutExpired):
            pass  # etcd unreachable for a moment (a kill): next sample

    def run(self) -> None:
        start = time.monotonic()
        with open(self.path, "w") as f:
            f.write("t_s,map_streams_bytes,snapshots_stream_bytes,"
                    "stream,bytes,messages,first_seq,...\n")
            while not self.stop.is_set():
                self.sample(time.monotonic() - start, f)
                self.stop.wait(self.every)
            self.sample(time.monotonic() - start, f)


def plot_stream_csv(csv_path: str, svg_path: str, kills: list[float] | None = None) -> None:
    """The sampler's CSV as an SVG line plot (no plotting package needed): the maps' streams'
    bytes (sum) and the snapshots stream's bytes (the bases) over time; kills as red ticks."""
    rows = []
    with open(csv_path) as f:
        next(f)
        for line in f:
            cells = line.strip().split(",")
            if len(cells) >= 3:
                rows.append((float(cells[0]), int(cells[1]), int(cells[2])))
    if not rows:
        return
    w, h, m = 900, 360, 60
    t_max = max(r[0] for r in rows) or 1.0
    y_max = max(max(r[1], r[2]) for r in rows) or 1

    def xy(t: float, y: int) -> str:
        return f"{m + (w - 2 * m) * t / t_max:.1f},{h - m - (h - 2 * m) * y / y_max:.1f}"
    lines = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" '
             f'font-family="sans-serif" font-size="12">',
             f'<rect width="{w}" height="{h}" fill="white"/>',
             f'<line x1="{m}" y1="{h - m}" x2="{w - m}" y2="{h - m}" stroke="black"/>',
             f'<line x1="{m}" y1="{m}" x2="{m}" y2="{h - m}" stroke="black"/>',
             f'<text x="{w / 2}" y="{h - 20}" text-anchor="middle">time (s), '
             f'0-{t_max:.0f}</text>',
             f'<text x="10" y="{m - 20}">bytes, 0-{y_max / 1e6:.1f} MB</text>']
    for t in kills or []:
        lines.append(f'<line x1="{xy(t, 0).split(",")[0]}" y1="{h - m}" '
                     f'x2="{xy(t, 0).split(",")[0]}" y2="{h - m + 8}" stroke="red"/>')
    for column, colour, label in ((1, "steelblue", "maps' streams"),
                                  (2, "darkorange", "snapshots stream (bases)")):
        points = " ".join(xy(r[0], r[column]) for r in rows)
        lines.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" '
                     f'points="{points}"/>')
        lines.append(f'<text x="{w - m - 200}" y="{m + 16 * column}" fill="{colour}">'
                     f'{label}</text>')
    lines.append("</svg>")
    with open(svg_path, "w") as f:
        f.write("\n".join(lines) + "\n")


def move_replica(status: dict, map_name: str, last: int) -> tuple[float, str, str, str]:
    """Moves `map_name`'s second replica to the shard without one (docs/cluster.md, "Move a
    map"): seconds until the new replica applied `last`, its log's restore line, the replica
    kept and the new one's shard."""
    placement_key = f"/placedb/{status['name']}/placement/{map_name}"
    placement = json.loads(etcd_prefix(status, placement_key)[placement_key])
    shards = [k.rsplit("/", 1)[1]
              for k in etcd_prefix(status, f"/placedb/{status['name']}/shards/")]
    new = next(s for s in sorted(shards) if s not in placement["replicas"])
    kept, moved = placement["replicas"]
    placement["epoch"] += 1
    placement["replicas"] = [kept, new]
    print(f"cluster_soak: moving {map_name} from {moved} to {new} (kept {kept})", file=sys.stderr)
    moved_at = time.monotonic()
    etcd_put(status, placement_key, json.dumps(placement))
    while applied_of(status, map_name).get(new, 0) < last:
        if time.monotonic() - moved_at > 600:
            raise RuntimeError(f"{new} did not catch up: {applied_of(status, map_name)}")
        time.sleep(0.05)
    took = time.monotonic() - moved_at
    restored = ""
    log = status["hosts"][int(new.split("-")[1])]["processes"]["shard"]["log"]
    with open(log, errors="replace") as f:
        for line in f:
            if map_name in line and "restored from" in line:
                restored = line.rstrip()
    return took, restored, kept, new


def replica(args, sdk) -> int:
    """`--places` places in one map, then the map moved to the third shard (docs/cluster.md,
    "Move a map"): seconds until the new replica has applied the stream's last place, restored
    from a live replica's checkpoint; then the other replica's shard is SIGKILLed and queries of
    stored frames must be answered by the new one (top match = the frame's own place)."""
    cluster = Cluster(tempfile.mkdtemp(prefix="placedb-replica-"))
    cluster.up(3, ["--placedb-server", args.placedb_server, "--roles", args.roles]
               + [f"--server-arg={a}" for a in args.server_arg or []])
    try:
        status = cluster.status()
        map_name = "replica-big"
        with sdk.Client(status["workers"][0]) as client:
            client.create_map(map_name, map_settings(sdk, True))
        acks, stop = Acks(), threading.Event()
        per_agent = -(-args.places // args.agents)
        workers = status["workers"]
        threads = [threading.Thread(target=agent_loop, daemon=True, args=(
            sdk, cluster, map_name, f"agent-{i}", per_agent,
            lambda a, s: synthetic_frame(sdk, a, s, args.features), acks, stop,
            lambda f, i=i: workers[(i + f) % len(workers)])) for i in range(args.agents)]
        start = time.monotonic()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        ingest_s = time.monotonic() - start
        last = max(max(ids) for ids in acks.by_frame.values())
        out("replica_places", acks.count(), "places")
        out("replica_ingest_rate", acks.count() / ingest_s, "frames/s")
        while min(applied_of(status, map_name).values() or [0]) < last or \
                len(applied_of(status, map_name)) < 2:
            if time.monotonic() - start > args.finish_timeout + ingest_s:
                raise RuntimeError(f"replicas did not apply {last}: {applied_of(status, map_name)}")
            time.sleep(0.5)
        out("replica_apply_behind_ingest", time.monotonic() - start - ingest_s, "s")
        took, restored, kept, new = move_replica(status, map_name, last)
        out("replica_new_serving", took, "s")
        if restored:
            print("cluster_soak: " + restored, file=sys.stderr)
        new_host = int(new.split("-")[1])
        # Only the new replica is left: every answer comes from it.
        cluster.kill_process(int(kept.split("-")[1]), "shard")
        rng = random.Random(args.seed)
        right = 0
        with sdk.Client(workers[new_host]) as client:
            for _ in range(args.replica_queries):
                (agent, sequence), ids = rng.choice(sorted(acks.by_frame.items()))
                (place,) = ids
                result = client.query(map_name, synthetic_frame(sdk, agent, sequence, args.features),
                                      top_k=1, timeout=10)
                right += bool(result.matches) and result.matches[0].place_id == place
        out("replica_queries_right", right / args.replica_queries, "share")
    finally:
        cluster.down(purge=not args.keep)
    return 0


# ---- self-test -----------------------------------------------------------------------------


class SelfTest(unittest.TestCase):
    def test_stalls(self):
        # Acks every 0.1 s except a 4 s gap after the kill at 10.
        times = [i / 10 for i in range(0, 101)] + [14.0 + i / 10 for i in range(0, 200)]
        self.assertAlmostEqual(stalls(times, [10.0], 30.0)[0], 4.0, places=6)
        self.assertEqual(stalls([], [5.0], 30.0), [30.0])
        # Acks stop before the kill and never resume in the window: the whole window.
        self.assertAlmostEqual(stalls([1.0, 2.0], [5.0], 30.0)[0], 30.0)
        # Every frame acknowledged at 3.0: a kill at 5 has nothing to stall; a kill at 2 is
        # measured up to 3.
        self.assertEqual(stalls([1.0, 2.0, 3.0], [5.0], 30.0, finished=3.0), [None])
        self.assertAlmostEqual(stalls([1.0, 2.0, 3.0], [2.0], 30.0, finished=3.0)[0], 1.0)

    def test_agent_stalls(self):
        acks = Acks()
        for i in range(100):  # agent a: steady; agent b: 3 s without an ack after the kill at 5
            acks.add("m", "a", i, i, i * 0.1)
            acks.add("m", "b", i, 1000 + i, i * 0.1 if i < 50 else 3.0 + i * 0.1)
        self.assertAlmostEqual(agent_stalls(acks, 100, [5.0], 30.0)[0], 3.0, places=6)
        self.assertEqual(agent_stalls(acks, 100, [20.0], 30.0), [None])

    def test_verify(self):
        acks = Acks()
        acks.add("a", "x", 0, 1, 0.0)
        acks.add("a", "x", 1, 2, 0.0)
        acks.add("a", "x", 1, 2, 0.1)  # a resent frame answered with its original id
        acks.add("b", "y", 0, 1, 0.0)
        self.assertEqual(verify(acks, {"a": [(1, "x", 0), (2, "x", 1)], "b": [(1, "y", 0)]}),
                         (0, 0))
        self.assertEqual(verify(acks, {"a": [(1, "x", 0)], "b": [(1, "y", 0)]}), (1, 0))
        acks.add("a", "x", 1, 3, 0.2)  # the same frame under a second id
        self.assertEqual(verify(acks, {"a": [(1, "x", 0), (2, "x", 1), (3, "x", 1)],
                                       "b": [(1, "y", 0)]}), (0, 2))

    def test_query_retry_accounting(self):
        def fail(_t):
            raise RuntimeError("unavailable")

        self.assertEqual(query_once_with_retry([lambda t: None, fail], 0.25), (True, False))
        self.assertEqual(query_once_with_retry([fail, lambda t: None], 0.25), (True, True))
        self.assertEqual(query_once_with_retry([fail, fail], 0.25), (False, True))
        self.assertEqual(query_once_with_retry([lambda t: time.sleep(0.3), fail], 0.25),
                         (False, False))

    def test_stream_plot(self):
        with tempfile.TemporaryDirectory() as d:
            csv_path = os.path.join(d, "s.csv")
            with open(csv_path, "w") as f:
                f.write("t_s,map_streams_bytes,snapshots_stream_bytes,...\n"
                        "0.0,0,0\n5.0,1000,0,S,1000,3,1\n10.0,200,5000,S,200,1,4\n")
            plot_stream_csv(csv_path, os.path.join(d, "s.svg"), [7.0])
            with open(os.path.join(d, "s.svg")) as f:
                svg = f.read()
            self.assertEqual(svg.count("<polyline"), 2)
            self.assertIn('stroke="red"', svg)

    def test_synthetic_frames_are_deterministic(self):
        class Sdk:
            class Frame:
                def __init__(self, **kw):
                    self.__dict__.update(kw)
        a = synthetic_frame(Sdk, "agent-1", 7)
        b = synthetic_frame(Sdk, "agent-1", 7)
        c = synthetic_frame(Sdk, "agent-1", 8)
        self.assertTrue((a.descriptors == b.descriptors).all())
        self.assertFalse((a.descriptors == c.descriptors).all())
        self.assertEqual(a.sequence, 7)

    def test_kill_schedule_on_engines(self):
        """The kill/restart part on real engines (no placedb roles): every kill takes a host's
        processes down and its restart brings them back; the JetStream meta leader survives."""
        cluster = Cluster(tempfile.mkdtemp(prefix="placedb-soak-selftest-"))
        cluster.up(3, ["--roles", "none"])
        try:
            rng = random.Random(1)
            for _ in range(2):
                host = rng.randrange(3)
                cluster.kill_host(host)
                s = cluster.status()
                self.assertFalse(s["hosts"][host]["up"])
                self.assertFalse(any(p["alive"] for p in s["hosts"][host]["processes"].values()))
                cluster.start_host(host)
                s = cluster.status()
                self.assertTrue(all(p["answers"] for p in s["hosts"][host]["processes"].values()))
            cluster.kill_process(1, "nats")
            cluster.kill_process(2, "nats")
            s = cluster.status()
            self.assertFalse(s["hosts"][1]["processes"]["nats"]["alive"])
            self.assertTrue(s["hosts"][1]["processes"]["etcd"]["alive"])
            cluster.start_host(1)
            cluster.start_host(2)
            s = cluster.status()
            self.assertTrue(all(p["answers"] for h in s["hosts"] for p in h["processes"].values()))
        finally:
            cluster.down(purge=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", nargs="?", default="soak",
                        choices=["soak", "replica", "self-test", "plot"])
    parser.add_argument("csv", nargs="?", help="plot mode: a --stream-csv file (SVG beside it)")
    parser.add_argument("--sdk", default=os.path.join(ROOT, "build", "client", "python"))
    parser.add_argument("--placedb-server",
                        default=os.path.join(ROOT, "build", "server", "placedb-server"))
    parser.add_argument("--server-arg", action="append", help="extra placedb-server argument")
    parser.add_argument("--roles", default="shard,worker",
                        help="placedb roles per host (tools/cluster_local.py up --roles)")
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--frames", type=int, default=1250)
    parser.add_argument("--agent-rate", type=float, default=7.0,
                        help="frames/s per agent in the soak (0: unpaced)")
    parser.add_argument("--kills", type=int, default=5)
    parser.add_argument("--kill-every", type=float, default=30.0)
    parser.add_argument("--down", type=float, default=10.0, help="seconds a killed host stays down")
    parser.add_argument("--query-rate", type=float, default=20.0)
    parser.add_argument("--deadline", type=float, default=0.25)
    parser.add_argument("--finish-timeout", type=float, default=600.0)
    parser.add_argument("--images", help="JPEG/PNG directory: image frames (with detection)")
    parser.add_argument("--workers", help="throughput mode: comma-separated worker counts")
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--worker-cpu", type=float, default=0.0,
                        help="throughput mode: cap each worker at this many cores (cgroup)")
    parser.add_argument("--seed", type=int, default=18)
    parser.add_argument("--compact-after-records", type=int,
                        help="soak: the workers' cluster.compact_after_records (compaction)")
    parser.add_argument("--stream-csv", help="soak: stream bytes over time (CSV)")
    parser.add_argument("--sample-every", type=float, default=2.0,
                        help="soak: seconds between stream samples")
    parser.add_argument("--places", type=int, default=100000, help="replica mode: the map's places")
    parser.add_argument("--features", type=int, default=500, help="replica mode: per frame")
    parser.add_argument("--replica-queries", type=int, default=50)
    parser.add_argument("--keep", action="store_true", help="keep the cluster's data and logs")
    args = parser.parse_args()
    if args.mode == "self-test":
        return 0 if unittest.main(argv=[sys.argv[0], "-v"], exit=False,
                                  defaultTest="SelfTest").result.wasSuccessful() else 1
    if args.mode == "plot":
        if not args.csv:
            parser.error("plot needs a CSV file")
        plot_stream_csv(args.csv, os.path.splitext(args.csv)[0] + ".svg")
        return 0
    sys.path.insert(0, args.sdk)
    import placedb as sdk  # noqa: E402 -- the build tree's SDK (generated stubs)

    args.image_paths = sorted(glob.glob(os.path.join(args.images, "*.jpg"))
                              + glob.glob(os.path.join(args.images, "*.png"))) if args.images else []
    if args.mode == "replica":
        return replica(args, sdk)
    return throughput(args, sdk) if args.workers else soak(args, sdk)


if __name__ == "__main__":
    sys.exit(main())
