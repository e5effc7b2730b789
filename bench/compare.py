#!/usr/bin/python3
"""Runs placedb's benchmarks and writes one table; with two builds, base and change side by side.

    bench/compare.py [--change build] [--base DIR | --base-rev REV] [--full] [--repeat 3]
                     [--only NAME,...] [--markdown FILE] [--json FILE] [--build] [--list]
                     [--dry-run] [--keep-base] [--timeout SECONDS]
    bench/compare.py --self-test

Every benchmark prints `name value unit` lines (bench/bench_output.h). Machine load drifts over
minutes on a shared 2-core machine, so base and change run alternately, benchmark by benchmark
and repeat by repeat (which side goes first alternates too), and the table shows each side's
median with its min-max and the load average before and after every run: a difference smaller
than the spread, or measured under a changing load, is noise. Nothing here judges a timing; the
exit code only says whether every run that was started completed (1 if one failed, 2 for a usage
error). Benchmarks whose binary, data, model or vocabulary is missing are skipped with a line
saying why. docs/benchmarks.md describes it.
"""

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Each benchmark: a name for the table, its binary under BUILD/bench, the arguments of the quick
# set (None: not in it; about 10 s or less per run on 2 cores so that the default of 2 builds x 3
# repeats stays within a few minutes) and of the full set, and what it reads. {vocabulary},
# {shared}, {models} and {workdir} are filled from the change's CMakeCache, so both builds see the
# same inputs. memory-flood is not here: it starts a server and measures memory, not speed.
BENCHMARKS = [
    {"name": "core", "binary": "placedb-bench-core",
     "quick": ["--vocabulary", "{vocabulary}", "--places", "1000,10000"],
     "full": ["--vocabulary", "{vocabulary}", "--places", "1000,10000,100000,1000000"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
    # Issue 29: learning a map's vocabulary and re-indexing with it; baseline the fixed one.
    {"name": "vocabulary-learning", "binary": "placedb-bench-vocabulary-learning",
     "quick": ["--vocabulary", "{vocabulary}", "--places", "10000"],
     "full": ["--vocabulary", "{vocabulary}", "--places", "10000,100000"],
     "needs": ["{vocabulary}", "{shared}/data/rtabmap-loop"]},
    {"name": "decode", "binary": "placedb-bench-decode",
     "quick": ["--rounds", "5"], "full": [],
     "needs": ["{shared}/data/rgbd-people"]},
    {"name": "correspondences", "binary": "placedb-bench-correspondences",
     "quick": [], "full": [],
     "needs": ["{shared}/data/rtabmap-loop"]},
    # Issue 31: re-ranking the 10 best candidates by verification; baseline the verifier before
    # issue 31 (and, through --base-rev, an earlier default).
    {"name": "verification", "binary": "placedb-bench-verification",
     "quick": ["--vocabulary", "{vocabulary}", "--queries", "10", "--rounds", "2"],
     "full": ["--vocabulary", "{vocabulary}", "--queries", "40", "--rounds", "3"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
    # Issue 32: relative pose per verified candidate; baseline the verification of the same pairs.
    {"name": "pose", "binary": "placedb-bench-pose",
     "quick": ["--rounds", "11"], "full": [],
     "needs": ["{shared}/data/slambook2-rgbd"]},
    {"name": "detector", "binary": "placedb-bench-detector",
     "quick": ["--models", "{models}", "--frames", "8", "--rounds", "1"],
     "full": ["--models", "{models}"],
     "needs": ["{models}/yolox_nano.onnx", "{models}/yolo-fastest-1.1-xl.weights",
               "{shared}/data/camvid"]},
    # Issue 17: end to end through the real server and placedb-load; its own same-run baseline
    # (the detector before issue 17), so it is worth running with one build too.
    {"name": "ingest-detect", "binary": "placedb-bench-ingest-detect",
     "quick": ["--models", "{models}", "--vocabulary", "{vocabulary}", "--dir", "{workdir}",
               "--seconds", "8", "--rounds", "1"],
     "full": ["--models", "{models}", "--vocabulary", "{vocabulary}", "--dir", "{workdir}",
              "--seconds", "20", "--rounds", "3"],
     "needs": ["{models}/yolox_nano.onnx", "{vocabulary}", "{shared}/data/camvid"]},
    {"name": "filtering", "binary": "placedb-bench-filtering",
     "quick": ["--vocabulary", "{vocabulary}", "--model", "{models}/yolox_nano.onnx",
               "--frames", "8", "--rounds", "1"],
     "full": ["--vocabulary", "{vocabulary}", "--model", "{models}/yolox_nano.onnx"],
     "needs": ["{vocabulary}", "{models}/yolox_nano.onnx", "{shared}/data/camvid"]},
    {"name": "rgbd", "binary": "placedb-bench-rgbd",
     "quick": ["--frames", "1000", "--wm", "500", "--passes", "1", "--unbounded-max", "1000"],
     "full": [],
     "needs": ["{sift_vocabulary}", "{shared}/data/rgbd-people"]},
    {"name": "storage-thumbnails", "binary": "placedb-bench-storage",
     "quick": ["--vocabulary", "{vocabulary}", "--dir", "{workdir}", "--only", "thumbnails"],
     "full": ["--vocabulary", "{vocabulary}", "--dir", "{workdir}", "--only", "thumbnails"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
    {"name": "storage-ingest", "binary": "placedb-bench-storage",
     "quick": None,
     "full": ["--vocabulary", "{vocabulary}", "--dir", "{workdir}", "--only", "ingest"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
    # Issue 17: precomputed features through the real server and load tester, and query latency
    # idle and beside 4 ingesting agents (bench/ingest_load.py; about 40 s per run quick).
    {"name": "ingest", "binary": "placedb-bench-ingest",
     "quick": ["--vocabulary", "{vocabulary}", "--source", "{shared}/data/rtabmap-loop",
               "--duration", "5", "--query-rate", "40", "--query-duration", "5",
               "--query-phases", "2"],
     "full": ["--vocabulary", "{vocabulary}", "--source", "{shared}/data/rtabmap-loop",
              "--duration", "15", "--query-rate", "50", "--query-duration", "10",
              "--query-phases", "3"],
     "needs": ["{vocabulary}", "{shared}/data/rtabmap-loop"]},
    # Issue 17: a 1M-place map built fast, reopened by the sequential scan and the parallel load
    # (about 6 GB of scratch under {workdir} while it runs; the base build may lack --only reopen).
    {"name": "storage-reopen-1m", "binary": "placedb-bench-storage",
     "quick": None,
     "full": ["--vocabulary", "{vocabulary}", "--dir", "{workdir}", "--only", "reopen",
              "--reopen", "1000000"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
    # Fig. 6, persist rates, dynamics, reopen at 10k and 100k, snapshots: the long one.
    {"name": "storage", "binary": "placedb-bench-storage",
     "quick": None,
     "full": ["--vocabulary", "{vocabulary}", "--dir", "{workdir}"],
     "needs": ["{vocabulary}", "{shared}/data/camvid"]},
]


class UsageError(Exception):
    pass


def parse_output(text):
    """The `name value unit` lines of a benchmark's stdout, in order, as (name, value, unit).

    Comment lines (`#`) and anything else that is not exactly three fields with a number in the
    middle are workload descriptions, not figures, and are ignored. A unit may be absent in
    principle; it is then empty.
    """
    figures = []
    for line in text.splitlines():
        fields = line.split()
        if not fields or fields[0].startswith("#") or len(fields) not in (2, 3):
            continue
        try:
            value = float(fields[1])
        except ValueError:
            continue
        figures.append((fields[0], value, fields[2] if len(fields) == 3 else ""))
    return figures


def read_cache(build_dir):
    """KEY -> (TYPE, VALUE) of BUILD/CMakeCache.txt."""
    path = os.path.join(build_dir, "CMakeCache.txt")
    if not os.path.isfile(path):
        raise UsageError(f"{build_dir} is not a CMake build directory (no CMakeCache.txt)")
    cache = {}
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            line = line.rstrip("\n")
            if not line or line.startswith(("#", "//")) or "=" not in line or ":" not in line:
                continue
            key_type, value = line.split("=", 1)
            key, _, kind = key_type.partition(":")
            cache[key] = (kind, value)
    return cache


def inputs_from_cache(cache, workdir):
    def get(key):
        return os.path.normpath(cache[key][1]) if key in cache and cache[key][1] else ""
    models = get("PLACEDB_MODELS_DIR")
    shared = get("PLACEDB_SHARED_DIR")
    # As placedb-bench-detector does: the shared models when the configured directory has none.
    if not os.path.isfile(os.path.join(models, "yolox_nano.onnx")) and shared:
        models = os.path.join(shared, "models")
    return {"vocabulary": get("PLACEDB_DEFAULT_VOCABULARY"),
            "sift_vocabulary": get("PLACEDB_SIFT_VOCABULARY"),
            "shared": shared, "models": models, "workdir": workdir}


def fill(items, inputs):
    return [item.format(**inputs) for item in items]


def load_average():
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            return [float(x) for x in f.read().split()[:3]]
    except OSError:
        return list(os.getloadavg())


def run_once(binary, args, timeout):
    """One run: (exit code, figures, seconds, load before, load after, stderr's tail)."""
    before = load_average()
    start = time.monotonic()
    try:
        done = subprocess.run([binary] + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, timeout=timeout, check=False)
        code, out, err = done.returncode, done.stdout, done.stderr
    except subprocess.TimeoutExpired as e:
        code, out, err = "timeout", e.stdout or "", f"killed after {timeout} s"
        out = out.decode() if isinstance(out, bytes) else out
    seconds = time.monotonic() - start
    tail = "\n".join(err.strip().splitlines()[-3:])
    return {"exit": code, "figures": parse_output(out), "seconds": round(seconds, 2),
            "load_before": before, "load_after": load_average(), "stderr": tail}


def median_and_range(values):
    if not values:
        return None
    return {"median": statistics.median(values), "min": min(values), "max": max(values),
            "n": len(values)}


def summarise(results, sides):
    """Rows of (benchmark, metric, unit, {side: median/min/max/n}), in first-seen order."""
    rows, index = [], {}
    for bench, runs in results.items():
        for side in sides:
            for run in runs.get(side, []):
                for name, value, unit in run["figures"]:
                    key = (bench, name, unit)
                    if key not in index:
                        index[key] = len(rows)
                        rows.append({"benchmark": bench, "metric": name, "unit": unit,
                                     "values": {s: [] for s in sides}})
                    rows[index[key]]["values"][side].append(value)
    for row in rows:
        row["stats"] = {s: median_and_range(row["values"][s]) for s in sides}
        base, change = row["stats"].get("base"), row["stats"].get("change")
        row["change_percent"] = row["change_points"] = None
        if base and change and row["unit"] == "%":
            # A percentage (an overhead, a cost) changes in points: a relative change of a value
            # near zero says nothing.
            row["change_points"] = change["median"] - base["median"]
        elif base and change and base["median"] != 0:
            difference = change["median"] - base["median"]
            row["change_percent"] = 100.0 * difference / abs(base["median"])
    return rows


def fmt(value):
    return "" if value is None else f"{value:.4g}"


def markdown(report):
    sides = report["sides"]
    lines = [f"# placedb benchmarks ({report['set']} set, {report['repeat']} repeat(s))", ""]
    lines.append(f"- finished (UTC): {report['date']}; host: {report['host']}; "
                 f"nproc: {report['nproc']}")
    lines.append(f"- load average (1, 5, 15 min) at start: {report['load_start']}; "
                 f"at end: {report['load_end']}")
    for side in sides:
        lines.append(f"- {side}: {report['builds'][side]}")
    lines.append("- base and change alternate run by run; medians of the repeats, min-max beside "
                 "them; change % = (change - base) / base (in points for % metrics). "
                 "No figure is judged here.")
    lines.append("")
    if len(sides) == 2:
        lines.append("| benchmark | metric | unit | base median | base min-max | change median "
                     "| change min-max | change % |")
        lines.append("|---|---|---|---:|---|---:|---|---:|")
    else:
        lines.append("| benchmark | metric | unit | median | min-max | n |")
        lines.append("|---|---|---|---:|---|---:|")
    for row in report["rows"]:
        cells = [row["benchmark"], row["metric"], row["unit"]]
        for side in sides:
            s = row["stats"][side]
            cells += (["-", "-"] if s is None else
                      [fmt(s["median"]), f"{fmt(s['min'])}-{fmt(s['max'])}"])
        if len(sides) == 2:
            pct, points = row["change_percent"], row["change_points"]
            cells.append(f"{points:+.3g} points" if points is not None else
                         "-" if pct is None else f"{pct:+.1f}")
        else:
            s = row["stats"][sides[0]]
            cells.append(str(s["n"]) if s else "0")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Runs (load average: 1-min before -> after)", ""]
    lines.append("| benchmark | build | run | exit | seconds | load before | load after |")
    lines.append("|---|---|---:|---|---:|---|---|")
    for run in report["runs"]:
        lines.append(f"| {run['benchmark']} | {run['side']} | {run['repeat']} | {run['exit']} | "
                     f"{run['seconds']} | {run['load_before'][0]:.2f} | "
                     f"{run['load_after'][0]:.2f} |")
    if report["skipped"] or report["failed"]:
        lines += ["", "## Skipped and failed", ""]
        for line in report["skipped"]:
            lines.append(f"- skipped: {line}")
        for line in report["failed"]:
            lines.append(f"- FAILED: {line}")
    return "\n".join(lines) + "\n"


def describe_build(build_dir, rev_note=""):
    cache = read_cache(build_dir)
    source = cache.get("CMAKE_HOME_DIRECTORY", ("", ""))[1]
    commit = ""
    if source:
        done = subprocess.run(["git", "-C", source, "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=False)
        if done.returncode == 0:
            commit = done.stdout.strip()
            dirty = subprocess.run(["git", "-C", source, "status", "--porcelain",
                                    "--untracked-files=no"],
                                   capture_output=True, text=True, check=False).stdout.strip()
            commit += " (uncommitted changes)" if dirty else ""
    build_type = cache.get("CMAKE_BUILD_TYPE", ("", "?"))[1]
    return f"{os.path.abspath(build_dir)} ({build_type}{', ' + commit if commit else ''}{rev_note})"


def configure_args(cache):
    """The change's own cache entries that decide the code and its inputs, for the base build.

    Only the project's options and the compiler/build type: the base gets the same compiler,
    flags and data paths, and nothing machine-generated (paths of the change's tree).
    """
    args = []
    for key, (kind, value) in sorted(cache.items()):
        wanted = key.startswith("PLACEDB_") or key in (
            "CMAKE_BUILD_TYPE", "CMAKE_CXX_COMPILER", "CMAKE_C_COMPILER", "CMAKE_CXX_FLAGS",
            "CMAKE_CXX_FLAGS_RELEASE")
        if wanted and kind not in ("INTERNAL", "STATIC", "UNINITIALIZED"):
            args.append(f"-D{key}:{kind}={value}")
    return args


def build_targets(build_dir, targets, log):
    """Builds each target on its own: an older revision may lack a benchmark, which is then
    skipped rather than failing the whole comparison. Returns the targets that built."""
    built = []
    for target in targets:
        done = subprocess.run(["cmake", "--build", build_dir, "-j", str(os.cpu_count() or 2),
                               "--target", target], stdout=log, stderr=subprocess.STDOUT,
                              check=False)
        if done.returncode == 0:
            built.append(target)
    return built


def build_base(rev, change_dir, targets, keep):
    """A temporary worktree at REV, configured like the change, with only the benchmark targets.

    Returns (build dir, cleanup function, targets that built, note)."""
    root = tempfile.mkdtemp(prefix="placedb-bench-base-")
    tree = os.path.join(root, "src")
    done = subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", tree, rev],
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        shutil.rmtree(root, ignore_errors=True)
        raise UsageError(f"--base-rev {rev}: git worktree add failed: {done.stderr.strip()}")

    def cleanup():
        if keep:
            print(f"# base worktree kept: {tree} (remove: git worktree remove --force {tree})",
                  file=sys.stderr)
            return
        subprocess.run(["git", "-C", REPO, "worktree", "remove", "--force", tree],
                       capture_output=True, check=False)
        shutil.rmtree(root, ignore_errors=True)

    build = os.path.join(tree, "build")
    cache = read_cache(change_dir)
    generator = cache.get("CMAKE_GENERATOR", ("", ""))[1]
    log_path = os.path.join(root, "build.log")
    print(f"# building base {rev} in {build} (log: {log_path})", file=sys.stderr)
    with open(log_path, "w", encoding="utf-8") as log:
        cmd = ["cmake", "-S", tree, "-B", build] + (["-G", generator] if generator else [])
        done = subprocess.run(cmd + configure_args(cache), stdout=log, stderr=subprocess.STDOUT,
                              check=False)
        if done.returncode != 0:
            cleanup()
            raise RuntimeError(f"configuring base {rev} failed; see {log_path}")
        built = build_targets(build, targets, log)
    if set(built) != set(targets):
        # Their benchmarks are skipped; the log goes with the worktree unless --keep-base.
        print(f"# not built at {rev}: {', '.join(sorted(set(targets) - set(built)))} "
              f"(--keep-base keeps {log_path})", file=sys.stderr)
    sha = subprocess.run(["git", "-C", tree, "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True, check=False).stdout.strip()
    return build, cleanup, built, f", --base-rev {rev} = {sha}"


def run_all(selected, builds, inputs, repeat, timeout, progress=True):
    """Runs every selected benchmark `repeat` times per build, alternating builds."""
    sides = list(builds)
    results, runs, skipped, failed = {}, [], [], []
    for bench in selected:
        name = bench["name"]
        missing = [p for p in fill(bench["needs"], inputs) if not p or not os.path.exists(p)]
        if missing:
            what = ", ".join(m or "(path not configured)" for m in missing)
            skipped.append(f"{name}: missing {what}")
            if progress:
                print(f"# skipped: {skipped[-1]}", file=sys.stderr, flush=True)
            continue
        binaries = {s: os.path.join(builds[s], "bench", bench["binary"]) for s in sides}
        absent = [f"{s} ({binaries[s]})" for s in sides if not os.access(binaries[s], os.X_OK)]
        if absent:
            skipped.append(f"{name}: no {bench['binary']} in {', '.join(absent)}")
            if progress:
                print(f"# skipped: {skipped[-1]}", file=sys.stderr, flush=True)
            continue
        results[name] = {s: [] for s in sides}
        args = fill(bench["args"], inputs)
        for r in range(repeat):
            # Which build goes first alternates, so neither always runs on a warmer machine.
            for side in (sides if r % 2 == 0 else list(reversed(sides))):
                if progress:
                    print(f"# {name} {side} {r + 1}/{repeat}: {bench['binary']} {' '.join(args)}",
                          file=sys.stderr, flush=True)
                run = run_once(binaries[side], args, timeout)
                runs.append({"benchmark": name, "side": side, "repeat": r + 1,
                             **{k: run[k] for k in ("exit", "seconds", "load_before",
                                                    "load_after")}})
                if run["exit"] != 0:
                    failed.append(f"{name} {side} run {r + 1}: exit {run['exit']}: {run['stderr']}")
                    continue
                results[name][side].append(run)
    return results, runs, skipped, failed


def make_report(results, runs, skipped, failed, builds, set_name, repeat, load_start):
    sides = list(builds)
    return {"set": set_name, "repeat": repeat, "sides": sides,
            "date": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
            "host": platform.node(), "nproc": os.cpu_count(),
            "load_start": load_start, "load_end": load_average(),
            "builds": builds, "rows": summarise(results, sides), "runs": runs,
            "skipped": skipped, "failed": failed}


def self_test():
    """Parser, statistics, table and the runner itself on canned output (ctest, label unit)."""
    canned = ("# workload: 12 views\nquery_top10_at_1000_places 0.06 ms\nnot a figure\n"
              "index_bytes 13.44 bytes\ncount 5\n  \nname value unit extra\n")
    assert parse_output(canned) == [("query_top10_at_1000_places", 0.06, "ms"),
                                    ("index_bytes", 13.44, "bytes"), ("count", 5.0, "")], \
        parse_output(canned)
    with tempfile.TemporaryDirectory(prefix="placedb-compare-test-") as tmp:
        # Two fake builds whose benchmark prints a figure given by the build, a fixed one, and a
        # metric only the change has; a third benchmark needs data that does not exist.
        builds = {}
        for side, value in (("base", "10"), ("change", "8")):
            bench_dir = os.path.join(tmp, side, "bench")
            os.makedirs(bench_dir)
            script = os.path.join(bench_dir, "fake-bench")
            with open(script, "w", encoding="ascii") as f:
                extra = "echo new_metric 3 ms\n" if side == "change" else ""
                f.write(f"#!/bin/sh\necho '# comment'\necho query_ms {value} ms\n"
                        f"echo places 1000 places\necho overhead {value} %\n{extra}")
            os.chmod(script, 0o755)
            builds[side] = os.path.join(tmp, side)
        selected = [{"name": "fake", "binary": "fake-bench", "args": [], "needs": []},
                    {"name": "needs-data", "binary": "fake-bench", "args": [],
                     "needs": ["{shared}/nothing-here"]},
                    {"name": "no-binary", "binary": "absent-bench", "args": [], "needs": []}]
        inputs = {"shared": tmp, "vocabulary": "", "sift_vocabulary": "", "models": "",
                  "workdir": tmp}
        results, runs, skipped, failed = run_all(selected, builds, inputs, 3, 30, progress=False)
        assert not failed, failed
        assert len(runs) == 6 and [r["side"] for r in runs[:4]] == ["base", "change", "change",
                                                                     "base"], runs
        assert any(s.startswith("needs-data: missing") for s in skipped), skipped
        assert any(s.startswith("no-binary: no absent-bench") for s in skipped), skipped
        report = make_report(results, runs, skipped, failed, builds, "test", 3, load_average())
        rows = {r["metric"]: r for r in report["rows"]}
        assert rows["query_ms"]["stats"]["base"]["median"] == 10
        assert abs(rows["query_ms"]["change_percent"] + 20.0) < 1e-9, rows["query_ms"]
        assert rows["places"]["change_percent"] == 0
        assert rows["new_metric"]["stats"]["base"] is None
        text = markdown(report)
        assert "| fake | query_ms | ms | 10 | 10-10 | 8 | 8-8 | -20.0 |" in text, text
        assert "| fake | new_metric | ms | - | - | 3 | 3-3 | - |" in text, text
        assert "- skipped: needs-data: missing" in text, text
        assert "| fake | overhead | % | 10 | 10-10 | 8 | 8-8 | -2 points |" in text, text
        json.dumps(report)
        # One build only: median, range, count.
        one = {"change": builds["change"]}
        results, runs, skipped, failed = run_all(selected[:1], one, inputs, 2, 30, progress=False)
        text = markdown(make_report(results, runs, skipped, failed, one, "test", 2, [0, 0, 0]))
        assert "| fake | query_ms | ms | 8 | 8-8 | 2 |" in text, text
        # A failing run is reported, not fatal.
        with open(os.path.join(builds["change"], "bench", "fake-bench"), "a",
                  encoding="ascii") as f:
            f.write("echo broken >&2\nexit 3\n")
        results, runs, skipped, failed = run_all(selected[:1], one, inputs, 1, 30, progress=False)
        assert failed and "exit 3: broken" in failed[0], failed
    print("compare.py self-test passed")
    return 0


def main(argv):
    parser = argparse.ArgumentParser(
        description="Run placedb's benchmarks (alternating two builds) and write one table.")
    parser.add_argument("--change", default="build",
                        help="build directory of the change (default: build)")
    base = parser.add_mutually_exclusive_group()
    base.add_argument("--base", help="build directory of the base (e.g. main's build)")
    base.add_argument("--base-rev", help="git revision to build as the base in a temporary "
                      "worktree, configured like --change (e.g. main)")
    parser.add_argument("--keep-base", action="store_true",
                        help="keep the --base-rev worktree and build afterwards")
    parser.add_argument("--full", action="store_true",
                        help="every benchmark at full size (long: reopen at 100k, ...)")
    parser.add_argument("--only", help="comma-separated benchmark names (see --list)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per build (default 3)")
    parser.add_argument("--timeout", type=int, default=3600, help="seconds per run")
    parser.add_argument("--build", action="store_true",
                        help="build the selected benchmark targets in --change first")
    parser.add_argument("--markdown", help="also write the table to this file")
    parser.add_argument("--json", help="write the whole report (every value) as JSON")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.add_argument("--dry-run", action="store_true",
                        help="print the commands that would run (and what is skipped), run none")
    parser.add_argument("--self-test", action="store_true", help=argparse.SUPPRESS)
    options = parser.parse_args(argv)
    if options.self_test:
        return self_test()

    set_name = "full" if options.full else "quick"
    if options.list:
        for bench in BENCHMARKS:
            quick = "quick+full" if bench["quick"] is not None else "full only"
            print(f"{bench['name']:20} {bench['binary']:32} {quick}")
        return 0
    if options.repeat < 1:
        raise UsageError("--repeat must be at least 1")
    selected = [dict(b, args=b["full"] if options.full else b["quick"]) for b in BENCHMARKS
                if options.full or b["quick"] is not None or options.only]
    if options.only:
        names = options.only.split(",")
        unknown = [n for n in names if n not in {b["name"] for b in BENCHMARKS}]
        if unknown:
            raise UsageError(f"--only: unknown benchmark(s) {', '.join(unknown)} (see --list)")
        selected = [dict(b, args=b["full"] if options.full or b["quick"] is None else b["quick"])
                    for b in BENCHMARKS if b["name"] in names]

    change_cache = read_cache(options.change)
    if options.base:
        read_cache(options.base)
    targets = sorted({b["binary"] for b in selected})
    if options.build:
        built = build_targets(options.change, targets, None)
        if set(built) != set(targets):
            print(f"# not built in {options.change}: {', '.join(set(targets) - set(built))}",
                  file=sys.stderr)
    workdir = tempfile.mkdtemp(prefix="placedb-bench-compare-")
    inputs = inputs_from_cache(change_cache, os.path.join(workdir, "storage"))
    cleanup, base_note = (lambda: None), ""
    try:
        base_dir = options.base
        if options.base_rev and options.dry_run:
            base_dir = options.change  # only the commands are printed; nothing is built
        elif options.base_rev:
            base_dir, cleanup, _, base_note = build_base(options.base_rev, options.change,
                                                         targets, options.keep_base)
        builds = {}
        if base_dir:
            builds["base"] = describe_build(base_dir, base_note)
        builds["change"] = describe_build(options.change)
        dirs = {"change": options.change}
        if base_dir:
            dirs = {"base": base_dir, "change": options.change}
        if options.dry_run:
            for bench in selected:
                print(f"{bench['name']}: {bench['binary']} {' '.join(fill(bench['args'], inputs))}"
                      f" (needs {', '.join(fill(bench['needs'], inputs))})")
            return 0
        load_start = load_average()
        results, runs, skipped, failed = run_all(selected, dirs, inputs, options.repeat,
                                                 options.timeout)
        report = make_report(results, runs, skipped, failed, builds, set_name, options.repeat,
                             load_start)
    finally:
        cleanup()
        shutil.rmtree(workdir, ignore_errors=True)
    text = markdown(report)
    sys.stdout.write(text)
    if options.markdown:
        with open(options.markdown, "w", encoding="utf-8") as f:
            f.write(text)
    if options.json:
        with open(options.json, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=1)
    return 1 if failed else 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except UsageError as e:
        print(f"compare.py: {e}", file=sys.stderr)
        sys.exit(2)
