#!/usr/bin/env python3
"""tools/cluster_local.py's engine part (issue 18): `up --roles none` on 3 hosts (network
namespaces as root, else loopback addresses), status, kill-host of the JetStream meta leader's
host (the others elect a new one; the killed host's ports are unreachable), start-host, down
(everything removed). The placedb roles are not started here: they need the shard and worker
roles (run `up` without --roles for them).

  python3 tests/cluster/cluster_local_test.py [-v]
"""

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import unittest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
LAUNCHER = os.path.join(ROOT, "tools", "cluster_local.py")


def launcher(directory, *args, check=True):
    result = subprocess.run([sys.executable, LAUNCHER, "--dir", directory, *args],
                            capture_output=True, text=True, timeout=180)
    if check and result.returncode != 0:
        raise AssertionError(f"cluster_local {' '.join(args)}: {result.returncode}\n"
                             f"{result.stdout}\n{result.stderr}")
    return result


def status(directory):
    return json.loads(launcher(directory, "status", "--json").stdout)


def reaches(host, port):
    try:
        with socket.create_connection((host, port), timeout=1):
            return True
    except OSError:
        return False


def running(pid):
    """True while `pid` is a live process (not a zombie: those have an empty command line)."""
    try:
        with open(f"/proc/{pid}/cmdline") as f:
            return bool(f.read())
    except OSError:
        return False


class ClusterLocalTest(unittest.TestCase):
    def test_engines_up_kill_meta_leader_host_start_down(self):
        with tempfile.TemporaryDirectory(prefix="placedb-cluster-local-") as directory:
            launcher(directory, "up", "--hosts", "3", "--roles", "none")
            try:
                s = status(directory)
                print(f"hosts: {s['kind']}", flush=True)
                if os.geteuid() == 0:
                    self.assertEqual(s["kind"], "netns")
                for host in s["hosts"]:
                    self.assertEqual(sorted(host["processes"]), ["etcd", "nats"])
                    for name, proc in host["processes"].items():
                        self.assertTrue(proc["answers"], f"host {host['host']} {name}")
                leader = ""
                for _ in range(100):
                    leader = status(directory)["meta_leader"]
                    if leader:
                        break
                    time.sleep(0.2)
                self.assertRegex(leader, r"^n[0-2]$")
                killed = int(leader[1:])
                address = s["hosts"][killed]["address"]
                self.assertTrue(reaches(address, 4222))

                launcher(directory, "kill-host", str(killed))
                after = status(directory)
                self.assertFalse(after["hosts"][killed]["up"])
                for name, proc in after["hosts"][killed]["processes"].items():
                    self.assertFalse(proc["alive"], name)
                self.assertFalse(reaches(address, 4222))
                self.assertFalse(reaches(address, 2379))
                if s["kind"] == "netns":
                    pids = subprocess.run(["ip", "netns", "pids", s["hosts"][killed]["netns"]],
                                          capture_output=True, text=True).stdout.split()
                    self.assertEqual(pids, [])
                new_leader = ""
                started = time.time()
                while time.time() - started < 60 and not new_leader:
                    new_leader = status(directory)["meta_leader"]
                    time.sleep(0.2)
                self.assertTrue(new_leader, "no new meta leader")
                self.assertNotEqual(new_leader, leader)
                print(f"cluster_local_meta_leader_reelected_s {time.time() - started:.1f} s")

                launcher(directory, "start-host", str(killed))
                back = status(directory)
                self.assertTrue(back["hosts"][killed]["up"])
                for name, proc in back["hosts"][killed]["processes"].items():
                    self.assertTrue(proc["answers"], name)
                etcd = subprocess.run(["etcdctl", "--endpoints", ",".join(back["etcd"]),
                                       "endpoint", "health"], capture_output=True, text=True)
                if etcd.returncode != 127:
                    self.assertEqual(etcd.returncode, 0, etcd.stdout + etcd.stderr)
            finally:
                s = status(directory)
                launcher(directory, "down", "--purge")
            self.assertFalse(os.path.exists(os.path.join(directory, "state.json")))
            if s["kind"] == "netns":
                names = subprocess.run(["ip", "netns", "list"], capture_output=True,
                                       text=True).stdout
                links = subprocess.run(["ip", "-br", "link"], capture_output=True,
                                       text=True).stdout
                for host in s["hosts"]:
                    self.assertNotIn(host["netns"], names)
                    self.assertNotIn(host["netns"][:-2] + "v", links)
            for host in s["hosts"]:
                for name, proc in host["processes"].items():
                    self.assertFalse(running(proc["pid"]), name)


if __name__ == "__main__":
    unittest.main()
