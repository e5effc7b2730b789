#!/usr/bin/python3
"""Ingest of precomputed features through gRPC, and query latency under that ingest (issue 17).

Runs the real `placedb-server` and `placedb-load` of a build (this script's own build when it is
installed as BUILD/bench/placedb-bench-ingest, or --build) on loopback, each run with a fresh
data directory, and prints `name value unit` lines (bench/bench_output.h's format):

1. throughput: `--agents` Ingest streams of precomputed ORB features (placedb-load --mode
   features, unpaced, durable acknowledgements: the server's default `storage.sync`) for
   `--duration` seconds: frames/s, ack latency p50/p99;
2. query under ingest, on one map preloaded with one pass of the frames: a query stream at a
   fixed rate (`--query-rate`, one query in flight) alone (idle), then the same queries while
   `--agents` streams ingest into the same map at full rate (loaded), `--query-phases` times
   alternately: query p50/p99 of each (medians over the phases) and the ratio of the p99s.

With --base-build DIR the same runs alternate with that build's server and load tester (base
first, then this build; the order alternates over --repeat), and its figures are printed as
`base_<name>`: the same-run baseline. Python 3 standard library only. No timing verdicts.
"""

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """One placedb-server of `build` on a free loopback port with a fresh data directory."""

    def __init__(self, build, vocabulary, workdir, threads, config=None):
        self.build = build
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.data = tempfile.mkdtemp(prefix="data-", dir=workdir)
        self.log = open(os.path.join(workdir, f"server-{self.port}.log"), "w")
        args = [os.path.join(build, "server", "placedb-server"), "--data-dir", self.data,
                "--listen", self.address, "--metrics-listen", "off", "--console-listen", "off",
                "--detector-model", "off", "--log-level", "warn",
                "--vocabulary", f"default={vocabulary}"]
        if threads:
            args += ["--threads", str(threads)]
        if config:
            args += ["--config", config]
        self.process = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT)
        cli = os.path.join(build, "client", "placedb")
        for _ in range(100):
            if self.process.poll() is not None:
                raise RuntimeError(f"placedb-server exited with {self.process.returncode}")
            if subprocess.run([cli, "--address", self.address, "health"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode == 0:
                return
            time.sleep(0.1)
        raise RuntimeError("placedb-server did not become healthy")

    def load(self, args, json_out):
        """Starts placedb-load against this server; returns the process."""
        return subprocess.Popen(
            [os.path.join(self.build, "client", "placedb-load"), "--address", self.address,
             "--json-out", json_out] + args,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(self):
        self.process.terminate()
        self.process.wait()
        self.log.close()
        shutil.rmtree(self.data, ignore_errors=True)


def finished(process, json_out, what):
    if process.wait() != 0:
        raise RuntimeError(f"{what}: placedb-load exited with {process.returncode}")
    with open(json_out) as f:
        return json.load(f)


def measure(build, options, workdir, config=None):
    """Every figure of one build, as (name, value, unit)."""
    figures = []
    source = [options.source, "--glob", "*.jpg", "--mode", "features"]
    server = Server(build, options.vocabulary, workdir, options.threads, config)
    try:
        out = os.path.join(workdir, "ingest.json")
        report = finished(server.load(source + ["--agents", str(options.agents),
                                                "--duration", str(options.duration)], out),
                          out, "ingest")
        ingest = report["rpc"]["ingest"]
        figures += [("ingest_features_fps", report["throughput_fps"], "frames/s"),
                    ("ingest_ack_p50", ingest["latency_ms"]["p50"], "ms"),
                    ("ingest_ack_p99", ingest["latency_ms"]["p99"], "ms"),
                    ("ingest_store_p50", ingest["stages_ms"]["store"]["p50"], "ms")]
    finally:
        server.stop()

    server = Server(build, options.vocabulary, workdir, options.threads, config)
    try:
        the_map = ["--map", "bench-query", "--keep-map"]
        out = os.path.join(workdir, "preload.json")
        finished(server.load(source + the_map + ["--agents", "2"], out), out, "preload")
        query = source + the_map + ["--agents", "1", "--query-ratio", "1",
                                    "--rate", str(options.query_rate),
                                    "--duration", str(options.query_duration)]
        # Loaded and idle phases alternate, so that the other processes of a shared machine
        # weigh on both alike; each figure is the median over the phases. Each idle phase comes
        # right after a loaded one: ingest grows the map, and a query's cost grows with it, so
        # the idle figure is taken on a map at least as large as any the loaded phase queried.
        idle, loaded, beside = [], [], []
        for phase in range(options.query_phases):
            out = os.path.join(workdir, f"loaded-{phase}.json")
            ingest_out = os.path.join(workdir, f"loaded-ingest-{phase}.json")
            ingesting = server.load(source + the_map + [
                "--agents", str(options.agents),
                "--duration", str(options.query_duration + 2)], ingest_out)
            time.sleep(1)  # the ingest streams are at full rate before the first query
            loaded.append(
                finished(server.load(query, out), out, "loaded queries")["rpc"]["query"])
            beside.append(finished(ingesting, ingest_out, "ingest beside queries")
                          ["throughput_fps"])
            out = os.path.join(workdir, f"idle-{phase}.json")
            idle.append(finished(server.load(query, out), out, "idle queries")["rpc"]["query"])

        def median(reports, key):
            return statistics.median(r["latency_ms"][key] for r in reports)
        idle_p99, loaded_p99 = median(idle, "p99"), median(loaded, "p99")
        figures += [("query_idle_p50", median(idle, "p50"), "ms"),
                    ("query_idle_p99", idle_p99, "ms"),
                    ("query_under_ingest_p50", median(loaded, "p50"), "ms"),
                    ("query_under_ingest_p99", loaded_p99, "ms"),
                    ("query_p99_ratio", loaded_p99 / idle_p99 if idle_p99 > 0 else 0, "x"),
                    ("ingest_beside_queries_fps", statistics.median(beside), "frames/s")]
    finally:
        server.stop()
    return figures


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--build", default=os.path.dirname(here),
                        help="the build whose server and load tester run (default: this "
                             "script's build, BUILD/bench/..)")
    parser.add_argument("--base-build", help="a second build measured alternately: base_ lines")
    parser.add_argument("--vocabulary", required=True)
    parser.add_argument("--source", required=True, help="image folder (features extracted once)")
    parser.add_argument("--agents", type=int, default=4)
    parser.add_argument("--duration", type=float, default=8)
    parser.add_argument("--query-rate", type=float, default=20, help="queries/s")
    parser.add_argument("--query-duration", type=float, default=8, help="seconds per phase")
    parser.add_argument("--query-phases", type=int, default=3,
                        help="idle and loaded phases, alternating; figures: their medians")
    parser.add_argument("--threads", type=int, default=0, help="server workers (0: its default)")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--config", help="server YAML configuration for this build's runs")
    options = parser.parse_args()
    for build in [options.build] + ([options.base_build] if options.base_build else []):
        for program in ("server/placedb-server", "client/placedb-load", "client/placedb"):
            if not os.access(os.path.join(build, program), os.X_OK):
                print(f"error: no {program} in {build}", file=sys.stderr)
                return 2
    print(f"# ingest_load: {options.agents} agents, precomputed ORB features of "
          f"{options.source}, {options.duration:g} s unpaced; queries {options.query_rate:g}/s "
          f"for {options.query_duration:g} s beside {options.agents} ingesting agents, then idle "
          f"on the grown map ({options.query_phases} times, medians); "
          f"nproc {os.cpu_count()}, load {os.getloadavg()[0]:.2f}")
    workdir = tempfile.mkdtemp(prefix="placedb-bench-ingest-")
    try:
        for r in range(options.repeat):
            sides = [("", options.build)]
            if options.base_build:
                sides = [("base_", options.base_build)] + sides
                if r % 2:
                    sides.reverse()
            for prefix, build in sides:
                config = options.config if build == options.build else None
                for name, value, unit in measure(build, options, workdir, config):
                    print(f"{prefix}{name} {value:.3f} {unit}", flush=True)
                print(f"# {prefix or 'change '}run {r + 1}: load {os.getloadavg()[0]:.2f}",
                      flush=True)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
