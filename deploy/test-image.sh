#!/usr/bin/env bash
# Builds the placedb container image without a Docker engine and tests what it ships.
#
#   deploy/test-image.sh [--cache DIR] [--models DIR] [--build-arg K=V]... [--context DIR] [--keep]
#                        [--timeout SECONDS] [--compose]
#
#  1. base: `debootstrap --variant=minbase bookworm` from this machine's own apt mirror (read
#     from /etc/apt/sources.list{,.d}), made to look like
#     debian:bookworm-slim (its dpkg path excludes, apt settings, deb822 sources), imported into
#     podman as localhost/debian:bookworm-slim;
#  2. build: `podman build --isolation chroot --format docker` of the Dockerfile with
#     BASE_IMAGE=localhost/debian:bookworm-slim (no registry is asked: --pull=never);
#  3. secrets: the image's placedb-init-secrets (what Compose's one-shot placedb-secrets service
#     runs) makes the CA, the server certificate and the tokens file (admin + prometheus) under
#     the rootfs' /run/secrets, printing the admin token once; a second run changes nothing; a
#     `reader` principal (read on every map) is added with `placedb-server tokens add`;
#  4. run: the image's root filesystem (podman create + export) runs placedb-server with chroot,
#     as the image's user, entrypoint, working directory and environment (TLS and tokens from
#     /run/secrets/placedb, as the image's ENV says), as PID 1 of its own PID namespace (as in a
#     container), on loopback ports;
#  5. checks: the image's HEALTHCHECK command turns healthy (placedb-healthcheck: `placedb --tls
#     health`); security: a plaintext client fails, no token and a wrong token are
#     UNAUTHENTICATED, /metrics answers 401 without or with wrong credentials and 200 with
#     Prometheus' (plain HTTP fails); the admin token creates a map, one Ingest stream and one
#     Query with the image's `placedb` CLI (TLS + token) find the right place (without a CLI in
#     the image: deploy/testing/grpc_probe.py, python3-grpcio, and the report says FALLBACK); the
#     reader token reads the map but DeleteMap is PERMISSION_DENIED and the map keeps its places;
#     the metrics endpoint counts them; Debian's prometheus with deploy/prometheus.yml (target
#     and secret files pointed at the test's; HTTPS + basic auth) has up{job="placedb"} == 1 and
#     the placedb_ series; after a second, small load every query of the Grafana dashboard
#     evaluates and the ingest rate is non-zero; SIGTERM shuts down cleanly (exit 0); a restart on
#     the same data directory (the VOLUME) finds every place; the data belongs to the image's
#     non-root user.
#  6. with --compose: `podman-compose up -d` of deploy/compose.yaml for real, with the image just
#     built: placedb-secrets makes the secrets and prints the admin token, placedb turns healthy
#     (its HEALTHCHECK), the image's CLI ingests and queries through the published port (TLS, the
#     printed admin token), Prometheus (Debian's package built into an image on the same base,
#     deploy/testing/prometheus.Dockerfile, over compose.yaml's by deploy/testing/compose.test.yaml:
#     no registry is reachable) scrapes placedb by its service name over HTTPS, then `down -v`.
#     Grafana is left out (no Debian package, no registry): the run says so.
#
# Needs root (debootstrap, chroot, mounts, podman) and reaches only the host's apt mirrors (packages)
# and 127.0.0.1. Installs podman, debootstrap, prometheus, python3-grpcio, python3-protobuf,
# protobuf-compiler, curl and opencv-doc (the test images) with apt-get when missing. Everything
# it makes lives in one temporary directory, removed at exit (--keep keeps it).
#
#   --cache DIR      keep the debootstrapped base (DIR/base-bookworm.tar) and podman's layer
#                    storage (DIR/storage) between runs: later runs skip debootstrap and reuse
#                    unchanged build layers. Default: nothing kept.
#   --models DIR     build arg MODELS (a directory of the context; default var/models, the
#                    detector is then included when tools/install_models.sh put it there);
#                    "" builds without a model
#   --build-arg K=V  passed to podman build (e.g. REQUIRE_CLI=0); repeatable
#   --context DIR    build context (default: this checkout)
#   --keep           keep the work directory (logs, rootfs) and print where it is
#   --timeout SEC    give up after this long in all (default 5400)
#   --compose        also run deploy/compose.yaml with podman-compose (step 6); installs
#                    podman-compose, runc (crun refuses hybrid cgroup hierarchies) and the CNI
#                    dnsname plugin (service names resolve inside the Compose network)
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/.." && pwd)"
context="$repo"
models="var/models"
cache=""
keep=0
timeout_s=5400
compose=0
original_args=("$@")
extra_build_args=()

say() { printf 'test-image: %s\n' "$*"; }
die() {
  printf 'test-image: FAILED: %s\n' "$*" >&2
  exit 1
}

while (($#)); do
  case "$1" in
    --cache) cache="$2"; shift 2 ;;
    --models) models="$2"; shift 2 ;;
    --build-arg) extra_build_args+=(--build-arg "$2"); shift 2 ;;
    --context) context="$(cd "$2" && pwd)"; shift 2 ;;
    --keep) keep=1; shift ;;
    --timeout) timeout_s="$2"; shift 2 ;;
    --compose) compose=1; shift ;;
    -h | --help) sed -n '2,62p' "$0"; exit 0 ;;
    *) echo "test-image: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

# The whole run is bounded: re-run under timeout(1), which signals the whole process group.
if [[ -z "${PLACEDB_TEST_IMAGE_BOUNDED:-}" ]]; then
  export PLACEDB_TEST_IMAGE_BOUNDED=1
  status=0
  timeout --signal=TERM --kill-after=60 "$timeout_s" "$0" "${original_args[@]}" || status=$?
  if ((status == 124)); then echo "test-image: FAILED: gave up after ${timeout_s} s" >&2; fi
  exit "$status"
fi

[[ "$(id -u)" -eq 0 ]] || die "needs root (debootstrap, chroot, mount, podman): run it with sudo"
[[ -f "$context/Dockerfile" ]] || die "no Dockerfile in $context"

# ---- packages ----------------------------------------------------------------------------------
need=()
packages=(podman debootstrap prometheus python3-grpcio python3-protobuf protobuf-compiler curl
  opencv-doc)
((compose)) && packages+=(podman-compose runc golang-github-containernetworking-plugin-dnsname)
for pkg in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if ((${#need[@]})); then
  say "installing ${need[*]}"
  apt-get update -q
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${need[@]}"
fi

# ---- work directory, cleanup -------------------------------------------------------------------
work="$(mktemp -d /var/tmp/placedb-test-image.XXXXXX)"
rootfs="$work/rootfs"
storage="$work/storage"
if [[ -n "$cache" ]]; then
  mkdir -p "$cache"
  cache="$(cd "$cache" && pwd)"
  storage="$cache/storage"
fi
# podman records its run and tmp directories with the storage: they move with it.
podman_state="$work"
[[ -n "$cache" ]] && podman_state="$cache"
mkdir -p "$work/tmp" "$podman_state/runroot" "$podman_state/libpod-tmp" "$rootfs"
export TMPDIR="$work/tmp"  # podman's build scratch space

podman_global=(--root "$storage" --runroot "$podman_state/runroot"
  --tmpdir "$podman_state/libpod-tmp" --storage-driver overlay --events-backend file
  --cgroup-manager cgroupfs)
pm() { podman "${podman_global[@]}" "$@"; }

server_pid=""   # the unshare wrapper of the server (its child is the server, PID 1 inside)
prom_pid=""
container=""
compose_cmd=()  # podman-compose with the test's files, once the Compose stack is started
image="localhost/placedb:test"
base_image="localhost/debian:bookworm-slim"

cleanup() {
  local status=$?
  set +e
  [[ -n "$server_pid" ]] && kill -KILL "$server_pid" 2>/dev/null && wait "$server_pid" 2>/dev/null
  [[ -n "$prom_pid" ]] && kill -TERM "$prom_pid" 2>/dev/null && wait "$prom_pid" 2>/dev/null
  if ((${#compose_cmd[@]})); then
    timeout 180 "${compose_cmd[@]}" down -v >>"$work/compose.log" 2>&1
    pm network rm -f "${compose_project}_default" >/dev/null 2>&1
  fi
  for m in "$rootfs/proc" "$rootfs/dev"; do
    if mountpoint -q "$m"; then umount "$m" 2>/dev/null || umount -l "$m"; fi
  done
  [[ -n "$container" ]] && pm rm -f "$container" >/dev/null 2>&1
  if [[ -z "$cache" ]]; then
    pm rm -a -f >/dev/null 2>&1
    pm rmi -a -f >/dev/null 2>&1
  fi
  # podman keeps its overlay directory mounted (a private bind mount): release it.
  findmnt -rn -o TARGET | grep -E "^($work|$storage)/" | sort -r | while read -r m; do
    umount "$m" 2>/dev/null || umount -l "$m"
  done
  if ((keep)); then
    say "work directory kept: $work"
  elif findmnt -rn -o TARGET | grep -q "^$work"; then
    echo "test-image: something is still mounted under $work; not deleting it:" >&2
    findmnt -rn -o TARGET | grep "^$work" >&2
  else
    rm -rf --one-file-system "$work"
  fi
  exit "$status"
}
trap cleanup EXIT
trap 'exit 143' TERM
trap 'exit 130' INT

# ---- timings -----------------------------------------------------------------------------------
declare -a timings=()
phase_name=""
phase_start=0
phase() {
  finish_phase
  phase_name="$1"
  phase_start=$SECONDS
  printf '\n==== test-image: %s ====\n' "$1"
}
finish_phase() {
  if [[ -n "$phase_name" ]]; then
    timings+=("$(printf '%-44s %5d s' "$phase_name" $((SECONDS - phase_start)))")
  fi
  phase_name=""
}

free_port() {
  /usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# The first URI this machine's apt sources use for `suite` (deb822 .sources or one-line .list):
# the image is built from the same mirror the host installs from, whatever it is.
apt_mirror_for() {
  local suite=$1 file uris suites
  for file in /etc/apt/sources.list.d/*.sources; do
    [[ -f "$file" ]] || continue
    # deb822 stanzas are separated by blank lines; comments start with '#'.
    awk -v suite="$suite" '
      /^[[:space:]]*#/ { next }
      /^[[:space:]]*$/ { if (uris != "" && found) { print uris; exit } uris = ""; found = 0; next }
      tolower($1) == "uris:" { uris = $2 }
      tolower($1) == "suites:" { for (i = 2; i <= NF; i++) if ($i == suite) found = 1 }
      END { if (uris != "" && found) print uris }' "$file" | head -n 1
  done | head -n 1 | grep . && return 0
  for file in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
    [[ -f "$file" ]] || continue
    awk -v suite="$suite" '$1 == "deb" {
        i = 2; if ($i ~ /^\[/) { while ($i !~ /\]$/) i++; i++ }
        if ($(i + 1) == suite) { print $i; exit } }' "$file"
  done | head -n 1 | grep .
}

# ---- 1. base image -----------------------------------------------------------------------------
phase "base image (debootstrap minbase)"
debian_mirror=$(apt_mirror_for bookworm) ||
  die "no apt source for bookworm in /etc/apt/sources.list{,.d}: the base image needs a Debian mirror"
security_mirror=$(apt_mirror_for bookworm-security) || security_mirror=""
say "Debian mirror (from this machine's apt sources): $debian_mirror"
base_tar="$work/base-bookworm.tar"
[[ -n "$cache" ]] && base_tar="$cache/base-bookworm.tar"
if [[ -s "$base_tar" ]]; then
  say "reusing $base_tar (delete it for a fresh debootstrap)"
else
  base="$work/base"
  timeout 1200 debootstrap --variant=minbase bookworm "$base" "$debian_mirror" \
    >"$work/debootstrap.log" 2>&1 || { tail -n 30 "$work/debootstrap.log" >&2; die "debootstrap"; }
  # What debian:bookworm-slim has: no docs/man/locales installed by dpkg, apt without caches
  # and recommends-as-usual, deb822 sources with updates and security.
  cat >"$base/etc/dpkg/dpkg.cfg.d/docker" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/linda/*
path-exclude /usr/share/lintian/overrides/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
path-exclude /usr/share/man/*
EOF
  cat >"$base/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
  printf 'Acquire::Languages "none";\n' >"$base/etc/apt/apt.conf.d/docker-no-languages"
  rm -f "$base/etc/apt/sources.list"
  {
    printf 'Types: deb\nURIs: %s\nSuites: bookworm bookworm-updates\nComponents: main\n' \
      "$debian_mirror"
    printf 'Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg\n'
    if [[ -n "$security_mirror" ]]; then
      printf '\nTypes: deb\nURIs: %s\nSuites: bookworm-security\nComponents: main\n' \
        "$security_mirror"
      printf 'Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg\n'
    fi
  } >"$base/etc/apt/sources.list.d/debian.sources"
  find "$base/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
  rm -rf "$base"/usr/share/{man,info,groff,lintian,linda}/* "$base"/var/lib/apt/lists/* \
    "$base"/var/cache/apt/*.bin "$base"/var/cache/apt/archives/*.deb "$base"/var/log/*.log
  tar -C "$base" --numeric-owner -cf "$base_tar" .
  rm -rf --one-file-system "$base"
fi
if ! pm image exists "$base_image"; then
  pm import --change 'CMD ["bash"]' \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' --message "debootstrap --variant=minbase bookworm" \
    "$base_tar" "$base_image" >/dev/null
fi
say "base image $base_image: $(pm image inspect --format '{{.Size}}' "$base_image" |
  awk '{ printf "%.0f MB", $1 / 1e6 }')"

# ---- 2. build ----------------------------------------------------------------------------------
phase "image build (podman, chroot isolation)"
build_args=(--build-arg "BASE_IMAGE=$base_image" --build-arg JOBS=2 --build-arg "MODELS=$models"
  "${extra_build_args[@]}")
if ! grep -q 'add_executable(placedb ' "$context/client/CMakeLists.txt" 2>/dev/null; then
  say "NOTE: the checkout has no placedb CLI target yet: building with REQUIRE_CLI=0"
  build_args+=(--build-arg REQUIRE_CLI=0)
fi
say "podman build ${build_args[*]} (log: $work/build.log)"
# On a shared machine someone's `pkill` may hit the compiler: a build stopped by a signal is
# retried (finished layers are reused); any other failure is final.
for attempt in 1 2 3; do
  if timeout 4500 podman "${podman_global[@]}" build --isolation chroot --format docker \
    --pull=never --layers "${build_args[@]}" -t "$image" -f "$context/Dockerfile" "$context" \
    >"$work/build.log" 2>&1; then
    break
  fi
  if ((attempt < 3)) &&
    grep -qE 'interrupted by user|subprocess exited on (terminated|killed|interrupt)' "$work/build.log"; then
    say "the build was stopped by a signal from outside (attempt $attempt): retrying"
    continue
  fi
  tail -n 60 "$work/build.log" >&2
  cp "$work/build.log" /var/tmp/placedb-test-image-build.log
  die "podman build (whole log: /var/tmp/placedb-test-image-build.log)"
done
# (Nothing matches when every layer came from the cache: not an error.)
{ grep -E '^(STEP [0-9]+/[0-9]+: FROM|Dockerfile:|runtime-libraries:)' "$work/build.log" || true; } | sed 's/^/  /'
say "image $image: $(pm image inspect --format '{{.Size}}' "$image" |
  awk '{ printf "%.0f MB", $1 / 1e6 }')"

# ---- 3. the image's filesystem and run settings ------------------------------------------------
phase "export the image's filesystem"
pm image inspect "$image" >"$work/inspect.json"
/usr/bin/python3 - "$work/inspect.json" "$work/image.env" <<'EOF'
import json, shlex, sys
image = json.load(open(sys.argv[1]))[0]
config = image.get("Config", {})
problems = []
def find_health(d):  # podman: top-level "Healthcheck"; docker: Config.Healthcheck
    for k, v in d.items():
        if k.lower() == "healthcheck" and v:
            return v
    return None
health = find_health(config) or find_health(image) or {}
test = health.get("Test") or []
if test[:1] == ["CMD-SHELL"]:
    test = ["/bin/sh", "-c", test[1]]
elif test[:1] == ["CMD"]:
    test = test[1:]
else:
    problems.append(f"no HEALTHCHECK command ({test})")
ports = sorted((config.get("ExposedPorts") or {}).keys())
if ports != ["50051/tcp", "9464/tcp"]:
    problems.append(f"EXPOSE: {ports}")
if "/var/lib/placedb" not in (config.get("Volumes") or {}):
    problems.append(f"VOLUME: {config.get('Volumes')}")
user = config.get("User") or "root"
if user.split(":")[0] in ("", "root", "0"):
    problems.append(f"runs as {user}")
env = config.get("Env") or []
if not any(e.startswith("PLACEDB_CONFIG=") for e in env):
    problems.append("no PLACEDB_CONFIG in the environment")
with open(sys.argv[2], "w") as out:
    def arr(name, values):
        out.write(f"{name}=(" + " ".join(shlex.quote(v) for v in values) + ")\n")
    arr("image_env", env)
    arr("image_entrypoint", config.get("Entrypoint") or [])
    arr("image_cmd", config.get("Cmd") or [])
    arr("image_healthcheck", test)
    out.write(f"image_user={shlex.quote(user)}\n")
    out.write(f"image_workdir={shlex.quote(config.get('WorkingDir') or '/')}\n")
    out.write(f"image_stopsignal={shlex.quote(config.get('StopSignal') or 'SIGTERM')}\n")
print(f"user {user}, workdir {config.get('WorkingDir')}, entrypoint {config.get('Entrypoint')}, "
      f"ports {ports}, volumes {list((config.get('Volumes') or {}).keys())}, "
      f"healthcheck {test} every {health.get('Interval', 0) / 1e9:.0f} s")
if problems:
    print("image settings: " + "; ".join(problems), file=sys.stderr)
    sys.exit(1)
EOF
# Sets image_env, image_entrypoint, image_cmd, image_healthcheck (arrays), image_user,
# image_workdir, image_stopsignal.
image_env=() image_entrypoint=() image_cmd=() image_healthcheck=() image_user="" image_workdir=""
# shellcheck source=/dev/null
source "$work/image.env"
container="$(pm create "$image" 2>>"$work/podman.log")"
pm export "$container" | tar -C "$rootfs" --numeric-owner -x
pm rm -f -v "$container" >/dev/null 2>>"$work/podman.log"  # -v: its anonymous VOLUME too
container=""
say "rootfs: $(du -sh --one-file-system "$rootfs" | cut -f1), binaries: $(
  cd "$rootfs/usr/local/bin" && echo placedb*)"

user_name="${image_user%%:*}"
uid="$(awk -F: -v u="$user_name" '$1 == u || $3 == u { print $3 }' "$rootfs/etc/passwd")"
gid="$(awk -F: -v u="$user_name" '$1 == u || $3 == u { print $4 }' "$rootfs/etc/passwd")"
[[ -n "$uid" && -n "$gid" ]] || die "user $image_user is not in the image's /etc/passwd"

mkdir -p "$rootfs/proc" "$rootfs/dev"
mount -t proc proc "$rootfs/proc"
mount --bind /dev "$rootfs/dev"

# ---- 4. secrets ----------------------------------------------------------------------------------
phase "secrets (placedb-init-secrets)"
# The image's own script, as root in the image's filesystem: /run/secrets stands for the
# placedb-secrets volume. Its log holds the admin token, printed once.
secrets_dir="$rootfs/run/secrets"
init_secrets() {
  env -i PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    chroot "$rootfs" /usr/local/bin/placedb-init-secrets /run/secrets
}
[[ -x "$rootfs/usr/local/bin/placedb-init-secrets" ]] || die "the image has no placedb-init-secrets"
init_secrets >"$work/init-secrets.log" 2>&1 || { cat "$work/init-secrets.log" >&2; die "placedb-init-secrets"; }
sed 's/pdb_[A-Za-z0-9_-]\{43\}/pdb_<redacted>/' "$work/init-secrets.log" | sed 's/^/  /'
admin_token="$(grep -oE '^pdb_[A-Za-z0-9_-]{43}$' "$work/init-secrets.log" | tail -n 1)"
[[ -n "$admin_token" ]] || die "placedb-init-secrets printed no admin token"
init_secrets >"$work/init-secrets2.log" 2>&1 || { cat "$work/init-secrets2.log" >&2; die "placedb-init-secrets (second run)"; }
if grep -qE 'pdb_[A-Za-z0-9_-]{43}' "$work/init-secrets2.log" || ! grep -q 'nothing changed' "$work/init-secrets2.log"; then
  cat "$work/init-secrets2.log" >&2
  die "a second placedb-init-secrets run must change nothing and print no token"
fi
for f in placedb/tls.crt placedb/tls.key placedb/ca.crt placedb/tokens.yaml prometheus/ca.crt \
  prometheus/metrics.password ca/ca.key; do
  [[ -s "$secrets_dir/$f" ]] || die "placedb-init-secrets did not write $f"
done
[[ "$(stat -c '%u %a' "$secrets_dir/placedb")" == "$uid 700" ]] ||
  die "$secrets_dir/placedb: $(stat -c '%u %a' "$secrets_dir/placedb"), expected $uid 700"
[[ "$(stat -c '%u %a' "$secrets_dir/placedb/tls.key")" == "$uid 600" ]] ||
  die "tls.key: $(stat -c '%u %a' "$secrets_dir/placedb/tls.key"), expected $uid 600"
[[ "$(stat -c '%u %a' "$secrets_dir/ca/ca.key")" == "0 600" ]] || die "ca/ca.key is not root's, 0600"
if grep -q "$admin_token" "$secrets_dir/placedb/tokens.yaml"; then
  die "the tokens file holds the admin token in clear"
fi
metrics_password="$(cat "$secrets_dir/prometheus/metrics.password")"
# A principal that may read every map (and nothing else), added with the image's
# `placedb-server tokens add` as the server's user (as deploy/README.md tells operators to).
reader_token="$(chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb-server tokens add \
  reader --tokens-file /run/secrets/placedb/tokens.yaml --read '*' 2>"$work/tokens-add.log")" ||
  { cat "$work/tokens-add.log" >&2; die "placedb-server tokens add reader"; }
[[ "$reader_token" =~ ^pdb_[A-Za-z0-9_-]{43}$ ]] || die "tokens add printed '$reader_token', not a token"
[[ "$(stat -c '%u %a' "$secrets_dir/placedb/tokens.yaml")" == "$uid 600" ]] ||
  die "tokens.yaml: $(stat -c '%u %a' "$secrets_dir/placedb/tokens.yaml"), expected $uid 600"
chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb-server tokens list \
  --tokens-file /run/secrets/placedb/tokens.yaml | sed 's/^/  tokens list: /' ||
  die "placedb-server tokens list"
openssl verify -CAfile "$secrets_dir/placedb/ca.crt" "$secrets_dir/placedb/tls.crt" >/dev/null ||
  die "the server certificate does not verify against ca.crt"
say "server certificate: $(openssl x509 -in "$secrets_dir/placedb/tls.crt" -noout -ext subjectAltName | tail -n 1 | sed 's/^ *//')"

grpc_port="$(free_port)"
metrics_port="$(free_port)"
prom_port="$(free_port)"
while [[ "$metrics_port" == "$grpc_port" ]]; do metrics_port="$(free_port)"; done
while [[ "$prom_port" == "$grpc_port" || "$prom_port" == "$metrics_port" ]]; do
  prom_port="$(free_port)"
done
run_env=("${image_env[@]}" "HOME=$image_workdir" "PLACEDB_LISTEN=127.0.0.1:$grpc_port"
  "PLACEDB_METRICS_LISTEN=127.0.0.1:$metrics_port" "PLACEDB_CONSOLE_LISTEN=off" "PLACEDB_THREADS=2")

# Starts the image's entrypoint as PID 1 of a new PID namespace, chrooted, as the image's user.
start_server() {
  local log="$1"
  # shellcheck disable=SC2016 # $1 and $@ are the inner shell's
  env -i "${run_env[@]}" unshare --pid --fork --kill-child=KILL \
    chroot --userspec="$uid:$gid" "$rootfs" \
    /bin/sh -c 'cd "$1" && shift && exec "$@"' sh "$image_workdir" \
    "${image_entrypoint[@]}" "${image_cmd[@]}" >"$log" 2>&1 &
  server_pid=$!
}
# The host PID of the server (the wrapper's child), once it has exec'd the entrypoint.
server_host_pid() {
  local child
  for _ in $(seq 1 100); do
    child="$(pgrep -P "$server_pid" | head -n 1 || true)"
    if [[ -n "$child" ]] && [[ "$(readlink "/proc/$child/exe" 2>/dev/null)" == */placedb-server ]]; then
      echo "$child"
      return 0
    fi
    sleep 0.1
  done
  return 1
}
# Runs the image's HEALTHCHECK command the way the engine would, until it passes.
wait_healthy() {
  local deadline=$((SECONDS + $1)) out="not run"
  while ((SECONDS < deadline)); do
    kill -0 "$server_pid" 2>/dev/null || return 1
    if ((have_cli)); then
      if out="$(env -i "${run_env[@]}" chroot --userspec="$uid:$gid" "$rootfs" \
        "${image_healthcheck[@]}" 2>&1)"; then
        echo "$out"
        return 0
      fi
    elif out="$(/usr/bin/python3 "$here/testing/grpc_probe.py" health "127.0.0.1:$grpc_port" \
      --ca-cert "$secrets_dir/placedb/ca.crt" 2>&1)"; then
      echo "$out"
      return 0
    fi
    sleep 1
  done
  echo "$out"
  return 1
}
stop_server() {
  local pid="$1" status=0
  kill -TERM "$pid"
  local deadline=$((SECONDS + 45))
  while kill -0 "$server_pid" 2>/dev/null && ((SECONDS < deadline)); do sleep 0.2; done
  kill -0 "$server_pid" 2>/dev/null && die "the server did not exit within 45 s of SIGTERM"
  wait "$server_pid" || status=$?
  server_pid=""
  return "$status"
}

have_cli=0
if [[ -x "$rootfs/usr/local/bin/placedb" ]]; then
  have_cli=1
else
  say "NOTE: the image has no placedb CLI: its HEALTHCHECK cannot pass; checking health with" \
    "deploy/testing/grpc_probe.py instead (FALLBACK)"
fi
cli_token="$admin_token"

# The image's CLI, chrooted, as the image's user, against the test server: TLS with the CA of the
# secrets, and the token in $cli_token (the admin's unless a check sets another).
cli_token=""
cli() {
  env -i "${run_env[@]}" "PLACEDB_ADDRESS=127.0.0.1:$grpc_port" "PLACEDB_TOKEN=$cli_token" \
    chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb \
    --tls --ca-cert /run/secrets/placedb/ca.crt "$@"
}
# The same without TLS (must fail against this server).
cli_plaintext() {
  env -i "${run_env[@]}" "PLACEDB_ADDRESS=127.0.0.1:$grpc_port" "PLACEDB_TOKEN=$cli_token" \
    chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb "$@"
}
# The Python probe with TLS (FALLBACK and the checks' second opinion); token: $cli_token.
probe() {
  local command="$1"
  shift
  PLACEDB_TOKEN="$cli_token" /usr/bin/python3 "$here/testing/grpc_probe.py" "$command" \
    "127.0.0.1:$grpc_port" --ca-cert "$secrets_dir/placedb/ca.crt" "$@"
}
count_places() {
  if ((have_cli)); then
    cli maps show imagetest --json | /usr/bin/python3 -c \
      'import json, sys; print(json.load(sys.stdin)["stats"]["places"])'
  else
    probe places --proto-root "$context" --map imagetest
  fi
}
# GET /metrics over HTTPS with the CA of the secrets; extra curl arguments (credentials) follow.
# Prints the HTTP status code, the body goes to $work/metrics.txt.
metrics_status() {
  curl -sS --max-time 10 --cacert "$secrets_dir/placedb/ca.crt" -o "$work/metrics.txt" \
    -w '%{http_code}' "$@" "https://127.0.0.1:$metrics_port/metrics" || true
}

# ---- 5. run and check --------------------------------------------------------------------------
phase "start placedb-server (chroot, PID 1)"
start_server "$work/server.log"
pid="$(server_host_pid)" || { cat "$work/server.log" >&2; die "the server did not start"; }
nspid="$(awk '/^NSpid:/ { print $NF }' "/proc/$pid/status")"
[[ "$nspid" == 1 ]] || die "the server is PID $nspid in its namespace, not 1"
rss_mib() { awk -v k="$2:" '$1 == k { printf "%.0f", $2 / 1024 }' "/proc/$1/status"; }
cpu_s() { awk -v hz="$(getconf CLK_TCK)" '{ printf "%.1f", ($14 + $15) / hz }' "/proc/$1/stat"; }
if ! out="$(wait_healthy 120)"; then
  echo "$out" >&2
  cat "$work/server.log" >&2
  die "not healthy within 120 s"
fi
if ((have_cli)); then
  say "HEALTHCHECK (${image_healthcheck[*]}): $out"
else
  say "health (FALLBACK probe): $out"
fi
# What the k8s readiness probe asks.
if ((have_cli)); then
  echo "  placedb-healthcheck placedb.v1.PlaceDb: $(env -i "${run_env[@]}" \
    chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb-healthcheck placedb.v1.PlaceDb)"
else
  probe health --service placedb.v1.PlaceDb | sed 's/^/  /'
fi
sed 's/^/  server: /' "$work/server.log"
say "server RSS when healthy: $(rss_mib "$pid" VmRSS) MiB"

phase "security: TLS, tokens, metrics credentials"
# A plaintext client cannot talk to the TLS port (health is open to any TLS client).
if ((have_cli)); then
  if out="$(cli_plaintext --timeout 5 health 2>&1)"; then
    die "a plaintext client got an answer: $out"
  fi
  say "plaintext client (placedb health without --tls): refused: $(tail -n 1 <<<"$out")"
fi
if out="$(/usr/bin/python3 "$here/testing/grpc_probe.py" health "127.0.0.1:$grpc_port" 2>&1)"; then
  die "a plaintext client got an answer: $out"
fi
say "plaintext client (grpc_probe.py without TLS): refused: $(tail -n 1 <<<"$out")"
# No token, a wrong token: UNAUTHENTICATED.
for token in "" "pdb_not-a-token-at-all"; do
  cli_token="$token"
  if ((have_cli)); then
    out="$(cli maps list 2>&1)" && die "maps list with token '$token' succeeded: $out"
    grep -q UNAUTHENTICATED <<<"$out" || die "maps list with token '$token': $out (expected UNAUTHENTICATED)"
  else
    out="$(probe call --proto-root "$context" ListMaps --expect UNAUTHENTICATED 2>&1)" || die "$out"
  fi
  if grep -qF -- "${token:-no token at all}" <<<"$out"; then die "the message shows the token: $out"; fi
  say "token '${token:-<none>}': $(tail -n 1 <<<"$out")"
done
cli_token="$admin_token"
# /metrics: HTTPS with basic auth (user = principal name, password = token).
code="$(metrics_status)"
[[ "$code" == 401 ]] || die "GET /metrics without credentials: HTTP $code (expected 401)"
code="$(metrics_status -u "prometheus:pdb_wrong")"
[[ "$code" == 401 ]] || die "GET /metrics with a wrong password: HTTP $code (expected 401)"
code="$(metrics_status -u "reader:$reader_token")"
[[ "$code" == 401 || "$code" == 403 ]] ||
  die "GET /metrics as reader (no metrics right): HTTP $code (expected 401 or 403)"
code="$(metrics_status -u "prometheus:$metrics_password")"
[[ "$code" == 200 ]] || die "GET /metrics with Prometheus' credentials: HTTP $code (expected 200)"
grep -q '^placedb_' "$work/metrics.txt" || die "GET /metrics (200) has no placedb_ series"
if curl -fsS --max-time 5 -u "prometheus:$metrics_password" -o /dev/null \
  "http://127.0.0.1:$metrics_port/metrics" 2>/dev/null; then
  die "/metrics answers plain HTTP"
fi
say "/metrics: 401 without credentials or with a wrong password, $(metrics_status -u "reader:$reader_token") as reader, 200 as prometheus, plain HTTP refused"

phase "prometheus scrape (deploy/prometheus.yml)"
# The secret files of the placedb-secrets volume (mounted at /etc/prometheus/secrets in Compose)
# are the rootfs' /run/secrets here; the server_name stays (the certificate names placedb).
sed -e "s|\"placedb:9464\"|\"127.0.0.1:$metrics_port\"|" \
  -e "s|\"localhost:9090\"|\"127.0.0.1:$prom_port\"|" \
  -e "s|/etc/prometheus/secrets/|$secrets_dir/|g" \
  -e 's|scrape_interval: 5s|scrape_interval: 1s|' \
  "$here/prometheus.yml" >"$work/prometheus.yml"
grep -q "127.0.0.1:$metrics_port" "$work/prometheus.yml" ||
  die "deploy/prometheus.yml has no \"placedb:9464\" target to point at the test server"
grep -q "password_file: $secrets_dir/prometheus/metrics.password" "$work/prometheus.yml" ||
  die "deploy/prometheus.yml does not read the password from the placedb-secrets volume"
promtool check config "$work/prometheus.yml" >/dev/null || die "promtool check config"
prometheus --config.file="$work/prometheus.yml" --storage.tsdb.path="$work/prometheus-data" \
  --web.listen-address="127.0.0.1:$prom_port" >"$work/prometheus.log" 2>&1 &
prom_pid=$!
prom_query() {  # prints the result vector as "labels value" lines; fails on a query error
  curl -fsS --max-time 10 -G --data-urlencode "query=$1" \
    "http://127.0.0.1:$prom_port/api/v1/query" | /usr/bin/python3 -c '
import json, sys
answer = json.load(sys.stdin)
if answer.get("status") != "success":
    sys.exit("query error: " + str(answer))
for sample in answer["data"]["result"]:
    print(json.dumps(sample["metric"], sort_keys=True), sample["value"][1])'
}
up=""
for _ in $(seq 1 60); do
  up="$(prom_query 'up{job="placedb"} == 1' 2>/dev/null || true)"
  [[ -n "$up" ]] && break
  sleep 1
done
[[ -n "$up" ]] || { tail -n 20 "$work/prometheus.log" >&2; die 'up{job="placedb"} == 1 not seen in 60 s'; }
say "prometheus: up{job=\"placedb\"} == 1: $up"

phase "ingest + query"
samples=/usr/share/doc/opencv-doc/examples/data
if ((have_cli)); then
  # The image's CLI, chrooted as the image's user, reading frames copied into the rootfs.
  frames="$rootfs/tmp/placedb-test"
  mkdir -p "$frames/first" "$frames/more"
  cp "$samples"/{aloeL.jpg,building.jpg,graf1.png,box_in_scene.png,home.jpg} "$frames/first/"
  cp "$samples/aloeR.jpg" "$frames/"
  chmod -R a+rX "$frames"
  cli maps create imagetest --json >"$work/create.json" || die "placedb maps create"
  cli ingest imagetest /tmp/placedb-test/first --json >"$work/ingest.json" ||
    die "placedb ingest: $(cat "$work/ingest.json")"
  cli query imagetest /tmp/placedb-test/aloeR.jpg --top-k 3 --json >"$work/query.json" ||
    die "placedb query"
  cli maps show imagetest --json >"$work/show.json" || die "placedb maps show"
  /usr/bin/python3 - "$work" <<'PY' || die "ingest/query through the image's CLI"
import json, os, sys
work = sys.argv[1]
load = lambda name: json.load(open(os.path.join(work, name)))
created, ingest, query, show = (load(n) for n in
                                ("create.json", "ingest.json", "query.json", "show.json"))
assert created["name"] == "imagetest", created
place_of = {}
for r in ingest["results"]:
    assert r["stored"], r
    place_of[r["place_id"]] = os.path.basename(r["name"])
    print(f"  placedb ingest: {os.path.basename(r['name'])} -> place {r['place_id']}, "
          f"{r['counts']['kept']}/{r['counts']['total']} descriptors kept, "
          f"{r['latency_ms']:.1f} ms")
assert ingest["stored"] == 5, ingest
ranked = [(place_of.get(m["place_id"], "?"), m["score"]) for m in query["matches"]]
print("  placedb query aloeR.jpg: " + ", ".join(f"{n} {s:.3f}" for n, s in ranked) +
      f" ({query['timings']['total_ms']:.1f} ms)")
assert ranked and ranked[0][0] == "aloeL.jpg", "expected aloeL.jpg first"
assert int(show["stats"]["places"]) == 5, show["stats"]
print(f"  placedb maps show: {show['stats']['places']} places, "
      f"{show['stats']['bytes_on_disk']} bytes on disk")
PY
else
  probe smoke --proto-root "$context" --map imagetest \
    --ingest "$samples/aloeL.jpg" "$samples/building.jpg" "$samples/graf1.png" \
    "$samples/box_in_scene.png" "$samples/home.jpg" \
    --query "$samples/aloeR.jpg" --expect "$samples/aloeL.jpg" | sed 's/^/  /' ||
    die "ingest/query smoke test (FALLBACK probe)"
fi
# The reader may read the map but not delete it; the map is unchanged.
cli_token="$reader_token"
if ((have_cli)); then
  cli maps show imagetest --json >/dev/null || die "the reader cannot read map imagetest"
  out="$(cli maps delete imagetest --yes 2>&1)" && die "the reader deleted map imagetest: $out"
  grep -q PERMISSION_DENIED <<<"$out" || die "reader's maps delete: $out (expected PERMISSION_DENIED)"
  out2="$(cli maps create readers-map 2>&1)" && die "the reader created a map: $out2"
  grep -q PERMISSION_DENIED <<<"$out2" || die "reader's maps create: $out2 (expected PERMISSION_DENIED)"
else
  probe call --proto-root "$context" GetMap --map imagetest --expect OK >/dev/null ||
    die "the reader cannot read map imagetest"
  out="$(probe call --proto-root "$context" DeleteMap --map imagetest --expect PERMISSION_DENIED 2>&1)" ||
    die "$out"
fi
grep -qF "$reader_token" <<<"$out" && die "the message shows the token: $out"
say "reader token: reads imagetest; DeleteMap: $(tail -n 1 <<<"$out")"
cli_token="$admin_token"
[[ "$(count_places)" == 5 ]] || die "map imagetest changed after the reader's calls"
metrics="$(curl -fsS --max-time 10 --cacert "$secrets_dir/placedb/ca.crt" \
  -u "prometheus:$metrics_password" "https://127.0.0.1:$metrics_port/metrics")" ||
  die "GET /metrics on 127.0.0.1:$metrics_port"
grep -qx 'placedb_frames_ingested_total{map="imagetest"} 5' <<<"$metrics" ||
  die "/metrics does not count the 5 ingested frames"
grep -qx 'placedb_places{map="imagetest"} 5' <<<"$metrics" || die "/metrics: placedb_places"
say "/metrics: $(grep -c '^placedb_' <<<"$metrics") placedb_ samples, 5 frames ingested, 5 places"

phase "prometheus queries (dashboard)"
seen=""
for _ in $(seq 1 30); do
  seen="$(prom_query 'placedb_frames_ingested_total{job="placedb", map="imagetest"} == 5' || true)"
  [[ -n "$seen" ]] && break
  sleep 1
done
[[ -n "$seen" ]] || die "prometheus has no placedb_frames_ingested_total{map=\"imagetest\"} == 5"
say "prometheus: placedb_frames_ingested_total: $seen"
# Counters born between two scrapes have no rate yet: more frames now that Prometheus has the
# series (opencv-doc's samples: some have too little structure and are rejected as invalid).
if ((have_cli)); then
  find "$samples" -maxdepth 1 -name '*.jpg' | sort | head -n 40 | xargs cp -t "$frames/more"
  chmod -R a+rX "$frames"
  # Exit 1 when a frame was refused with an error: judged from the summary instead.
  cli ingest imagetest /tmp/placedb-test/more --agents 2 --json >"$work/more.json" || true
  /usr/bin/python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
stored, frames, rejected = r["stored"], r["frames"], r["rejected"]["total"]
errors, stream_errors = r["errors"]["frames"], r["stream_errors"]
print(f"  placedb ingest --agents 2: {stored} of {frames} frames stored, {rejected} rejected "
      f"(too few static descriptors), {errors} errors, stream errors {stream_errors}")
sys.exit(0 if stored >= 20 and not stream_errors else 1)' "$work/more.json" ||
    die "the second ingest (its summary: $work/more.json)"
  for f in "$frames"/more/*.jpg; do cli query imagetest "${f#"$rootfs"}" >/dev/null; done
else
  probe load --proto-root "$context" --map imagetest --images "$samples" --frames 40 --streams 2 \
    --queries 20 | sed 's/^/  /' || die "the second load"
fi
sleep 4  # a few more scrapes
# Every query of the Grafana dashboard must evaluate ($variables = all, $__rate_interval = 1m).
/usr/bin/python3 -c '
import json, sys
dash = json.load(open(sys.argv[1]))
def panels(ps):
    for p in ps:
        yield p
        yield from panels(p.get("panels", []))
for p in panels(dash["panels"]):
    for t in p.get("targets", []):
        print(p["title"] + "\t" + t["expr"])
' "$here/grafana/dashboards/placedb.json" >"$work/dashboard-queries.tsv"
queries=0
with_data=0
no_data=()
while IFS=$'\t' read -r title expr; do
  q="${expr//\$__rate_interval/1m}"
  q="${q//\$instance/.*}"
  q="${q//\$map/.*}"
  result="$(prom_query "$q")" || die "dashboard panel \"$title\": query fails: $q"
  queries=$((queries + 1))
  if [[ -n "$result" ]]; then
    with_data=$((with_data + 1))
  else
    no_data+=("$title")
  fi
done <"$work/dashboard-queries.tsv"
say "dashboard: $queries queries evaluate, $with_data return data"
if ((${#no_data[@]})); then say "  no data in this run (expected: nothing of the kind happened):"; fi
for title in "${no_data[@]}"; do say "    $title"; done
for q in 'sum by (map) (rate(placedb_frames_ingested_total[1m])) > 0' \
  'histogram_quantile(0.5, sum by (le, stage) (rate(placedb_stage_seconds_bucket{stage="total"}[1m])))'; do
  r="$(prom_query "$q")"
  [[ -n "$r" ]] || die "no data for $q"
  say "  $q -> $r"
done

places_before="$(count_places)"

say "server after the loads: RSS $(rss_mib "$pid" VmRSS) MiB (peak $(rss_mib "$pid" VmHWM) MiB)," \
  "CPU $(cpu_s "$pid") s, $places_before places"

phase "graceful stop (SIGTERM to PID 1)"
stop_server "$pid" || die "exit status $? after SIGTERM (expected 0)"
grep -q 'shutdown complete' "$work/server.log" || die "no 'shutdown complete' in the server log"
say "exit status 0: $(grep 'shutdown complete' "$work/server.log" | sed 's/^.* info //')"
if ((have_cli)) && env -i "${run_env[@]}" chroot --userspec="$uid:$gid" "$rootfs" \
  "${image_healthcheck[@]}" >/dev/null 2>&1; then
  die "the HEALTHCHECK passes with the server stopped"
fi
others="$(find "$rootfs/var/lib/placedb" ! -uid "$uid" | head -n 5)"
[[ -z "$others" ]] || die "files in the data volume not owned by $image_user: $others"
say "data volume: $(du -sh "$rootfs/var/lib/placedb" | cut -f1), every file owned by $image_user ($uid)"

phase "restart on the same volume"
start_server "$work/server2.log"
pid="$(server_host_pid)" || { cat "$work/server2.log" >&2; die "the server did not restart"; }
out="$(wait_healthy 120)" || { cat "$work/server2.log" >&2; die "not healthy after restart"; }
places="$(count_places)"
[[ "$places" == "$places_before" ]] ||
  die "after a restart the map has $places places, not $places_before"
say "after restart: map imagetest has $places places, as before"
stop_server "$pid" || die "exit status $? after SIGTERM (expected 0)"

# ---- 6. Compose ----------------------------------------------------------------------------------
if ((compose)); then
  phase "compose: podman-compose up + checks + down"
  compose_dir="$work/compose"
  mkdir -p "$compose_dir"
  # Containers run with runc (crun refuses hybrid cgroup hierarchies; runc runs on v1, hybrid
  # and v2) and with resource limits this session may set: podman's defaults (open files
  # 1048576, ...) are refused where raising limits is not allowed (no CAP_SYS_RESOURCE, some
  # sandboxes), so the first of these settings under which a container starts is used.
  # podman-compose runs `podman`: the wrapper gives it the test's storage and these settings.
  {
    printf '#!/bin/sh\nexport CONTAINERS_CONF=%q\nexec podman' "$compose_dir/containers.conf"
    printf ' %q' "${podman_global[@]}" --runtime runc
    printf ' "$@"\n'
  } >"$compose_dir/podman"
  chmod 755 "$compose_dir/podman"
  cpm() { "$compose_dir/podman" "$@"; }
  nofile="$(ulimit -Hn)"
  [[ "$nofile" == unlimited ]] && nofile=1048576
  started=""
  for limits in "" "\"nofile=$nofile:$nofile\"" "\"nofile=$nofile:$nofile\", \"nproc=32768:32768\"" \
    "\"nofile=$nofile:$nofile\", \"nproc=4096:4096\""; do
    printf '[containers]\ndefault_ulimits = [%s]\n' "$limits" >"$compose_dir/containers.conf"
    if out="$(timeout 120 "$compose_dir/podman" run --rm --network none "$base_image" true 2>&1)"; then
      started=1
      break
    fi
  done
  [[ -n "$started" ]] || die "this machine cannot run a container (podman run --runtime runc): $out"
  say "containers run with runc, ulimits [${limits:-the podman defaults}]"

  # Prometheus: Debian's package on the same base (no registry: prom/prometheus cannot be pulled).
  prom_image="localhost/placedb-test-prometheus:debian"
  timeout 1200 podman "${podman_global[@]}" build --isolation chroot --format docker \
    --pull=never --layers --build-arg "BASE_IMAGE=$base_image" -t "$prom_image" \
    -f "$here/testing/prometheus.Dockerfile" "$here/testing" >"$work/prometheus-build.log" 2>&1 ||
    { tail -n 30 "$work/prometheus-build.log" >&2; die "building $prom_image"; }
  prom_version="$(cpm run --rm --network none --entrypoint /usr/bin/prometheus "$prom_image" \
    --version 2>&1 | awk 'NR == 1 { print $3 }' || true)"
  say "prometheus image $prom_image: Debian's prometheus ${prom_version:-?}," \
    "$(pm image inspect --format '{{.Size}}' "$prom_image" | awk '{ printf "%.0f MB", $1 / 1e6 }')"

  c_grpc="$(free_port)"
  c_metrics="$(free_port)"
  c_prom="$(free_port)"
  while [[ "$c_metrics" == "$c_grpc" ]]; do c_metrics="$(free_port)"; done
  while [[ "$c_prom" == "$c_grpc" || "$c_prom" == "$c_metrics" ]]; do c_prom="$(free_port)"; done
  compose_project="placedb-test-$$"
  export PLACEDB_IMAGE="$image" PLACEDB_TEST_PROMETHEUS_IMAGE="$prom_image" \
    PLACEDB_PUBLISH_ADDRESS=127.0.0.1 PLACEDB_PUBLISH_GRPC_PORT="$c_grpc" \
    PLACEDB_PUBLISH_METRICS_PORT="$c_metrics" PROMETHEUS_PUBLISH_PORT="$c_prom" PLACEDB_THREADS=2
  compose_cmd=(podman-compose --podman-path "$compose_dir/podman" -p "$compose_project"
    -f "$here/compose.yaml" -f "$here/testing/compose.test.yaml")
  say "podman-compose $(podman-compose version 2>/dev/null | awk '/podman-compose/ { print $NF; exit }'):" \
    "up -d placedb-secrets placedb prometheus (project $compose_project; ports 127.0.0.1:$c_grpc," \
    "$c_metrics, $c_prom)"
  say "  grafana is left out: grafana/grafana-oss cannot be pulled here (no registry) and Debian" \
    "has no grafana package; its dashboard's queries were checked against Prometheus above"
  timeout 600 "${compose_cmd[@]}" up -d placedb-secrets placedb prometheus >"$work/compose.log" 2>&1 ||
    { tail -n 40 "$work/compose.log" >&2; die "podman-compose up"; }
  c_secrets="${compose_project}_placedb-secrets_1"
  c_placedb="${compose_project}_placedb_1"
  c_prometheus="${compose_project}_prometheus_1"
  # The one-shot secrets service: exit status 0, the admin token in its log (README's way).
  status="$(timeout 120 "$compose_dir/podman" wait "$c_secrets" 2>&1)" ||
    die "placedb-secrets did not finish: $status"
  [[ "$status" == 0 ]] || {
    timeout 60 "${compose_cmd[@]}" logs placedb-secrets >&2 || true
    die "placedb-secrets exited with status $status"
  }
  timeout 60 "${compose_cmd[@]}" logs placedb-secrets >"$work/compose-secrets.log" 2>&1 || true
  compose_token="$(grep -oE '^pdb_[A-Za-z0-9_-]{43}$' "$work/compose-secrets.log" | tail -n 1 || true)"
  [[ -n "$compose_token" ]] || { cat "$work/compose-secrets.log" >&2; die "podman-compose logs placedb-secrets: no admin token"; }
  say "placedb-secrets: exit 0; its log holds the admin token (podman-compose logs placedb-secrets)"
  # Healthy: no systemd timer runs podman's healthchecks on this machine, so the test runs the
  # image's HEALTHCHECK the way the timer would (podman healthcheck run), until it passes.
  health=""
  deadline=$((SECONDS + 180))
  while ((SECONDS < deadline)); do
    cpm healthcheck run "$c_placedb" >/dev/null 2>&1 || true
    health="$(cpm inspect --format '{{.State.Health.Status}}' "$c_placedb" 2>/dev/null || true)"
    [[ "$health" == healthy ]] && break
    sleep 1
  done
  if [[ "$health" != healthy ]]; then
    cpm ps -a >&2 || true
    cpm logs "$c_placedb" 2>&1 | tail -n 30 >&2 || true
    die "placedb is not healthy within 180 s (state: ${health:-none})"
  fi
  say "placedb: healthy after $((SECONDS - deadline + 180)) s (restarts: $(cpm inspect \
    --format '{{.RestartCount}}' "$c_placedb" 2>/dev/null || echo '?'); podman-compose does not" \
    "wait for service_completed_successfully, the restart policy covers a start before the secrets)"

  # Clients outside the stack: the CA and Prometheus' password from the secrets volume.
  secrets_mount="$(cpm volume inspect --format '{{.Mountpoint}}' "${compose_project}_placedb-secrets")"
  cp "$secrets_mount/placedb/ca.crt" "$rootfs/tmp/compose-ca.crt"
  chmod 644 "$rootfs/tmp/compose-ca.crt"
  c_password="$(cat "$secrets_mount/prometheus/metrics.password")"
  if ((have_cli)); then
    ccli() {
      env -i "${run_env[@]}" "PLACEDB_ADDRESS=127.0.0.1:$c_grpc" "PLACEDB_TOKEN=$1" \
        chroot --userspec="$uid:$gid" "$rootfs" /usr/local/bin/placedb \
        --tls --ca-cert /tmp/compose-ca.crt "${@:2}"
    }
    out="$(ccli "" maps list 2>&1)" && die "maps list without a token succeeded: $out"
    grep -q UNAUTHENTICATED <<<"$out" || die "maps list without a token: $out"
    ccli "$compose_token" maps create composetest --json >/dev/null || die "placedb maps create"
    ccli "$compose_token" ingest composetest /tmp/placedb-test/first --json \
      >"$work/compose-ingest.json" || die "placedb ingest: $(cat "$work/compose-ingest.json")"
    ccli "$compose_token" query composetest /tmp/placedb-test/aloeR.jpg --top-k 3 --json \
      >"$work/compose-query.json" || die "placedb query"
    /usr/bin/python3 - "$work/compose-ingest.json" "$work/compose-query.json" <<'PY' ||
import json, os, sys
ingest, query = (json.load(open(p)) for p in sys.argv[1:3])
names = {r["place_id"]: os.path.basename(r["name"]) for r in ingest["results"] if r["stored"]}
assert ingest["stored"] == 5, ingest
ranked = [(names.get(m["place_id"], "?"), m["score"]) for m in query["matches"]]
print("  placedb (TLS, admin token) via the published port: ingest 5 of 5 stored; query aloeR.jpg: "
      + ", ".join(f"{n} {s:.3f}" for n, s in ranked))
assert ranked and ranked[0][0] == "aloeL.jpg", "expected aloeL.jpg first"
PY
      die "ingest + query through the Compose stack"
  else
    /usr/bin/python3 "$here/testing/grpc_probe.py" smoke "127.0.0.1:$c_grpc" \
      --ca-cert "$rootfs/tmp/compose-ca.crt" --proto-root "$context" --map composetest \
      --ingest "$samples/aloeL.jpg" "$samples/building.jpg" "$samples/graf1.png" \
      "$samples/box_in_scene.png" "$samples/home.jpg" --query "$samples/aloeR.jpg" \
      --expect "$samples/aloeL.jpg" --token "$compose_token" | sed 's/^/  /' ||
      die "ingest/query smoke test through the Compose stack (FALLBACK probe)"
  fi
  code="$(curl -sS --max-time 10 --cacert "$rootfs/tmp/compose-ca.crt" -o "$work/compose-metrics.txt" \
    -w '%{http_code}' -u "prometheus:$c_password" "https://127.0.0.1:$c_metrics/metrics" || true)"
  [[ "$code" == 200 ]] || die "GET https://127.0.0.1:$c_metrics/metrics as prometheus: HTTP $code"
  grep -qx 'placedb_frames_ingested_total{map="composetest"} 5' "$work/compose-metrics.txt" ||
    die "the published /metrics does not count the 5 frames"
  say "published /metrics (HTTPS, basic auth): 200, placedb_frames_ingested_total{map=\"composetest\"} 5"

  # Prometheus in the stack scrapes placedb by its service name (https://placedb:9464).
  prom_port="$c_prom"  # prom_query asks the stack's Prometheus from here on
  seen=""
  deadline=$((SECONDS + 120))
  while ((SECONDS < deadline)); do
    seen="$(prom_query 'placedb_frames_ingested_total{job="placedb", map="composetest"} == 5' 2>/dev/null || true)"
    [[ -n "$seen" ]] && break
    sleep 1
  done
  if [[ -z "$seen" ]]; then
    curl -sS --max-time 10 "http://127.0.0.1:$c_prom/api/v1/targets" >&2 || true
    cpm logs "$c_prometheus" 2>&1 | tail -n 20 >&2 || true
    die "the stack's Prometheus has no placedb_frames_ingested_total{map=\"composetest\"} == 5 within 120 s"
  fi
  say "prometheus (compose): up{job=\"placedb\"}: $(prom_query 'up{job="placedb"}'); $seen"

  timeout 180 "${compose_cmd[@]}" down -v >>"$work/compose.log" 2>&1 ||
    { tail -n 20 "$work/compose.log" >&2; die "podman-compose down -v"; }
  left="$(cpm ps -a -q --filter "label=io.podman.compose.project=$compose_project")"
  [[ -z "$left" ]] || die "containers left after down: $left"
  left="$(cpm volume ls -q --filter "label=io.podman.compose.project=$compose_project")"
  [[ -z "$left" ]] || die "volumes left after down -v: $left"
  # podman-compose 1.0.3's down removes containers without -v: placedb-secrets' anonymous volume
  # (the image's VOLUME, which that service does not mount) stays. This storage is the test's own.
  cpm volume prune -f >/dev/null 2>&1 || true
  compose_cmd=()
  pm network rm -f "${compose_project}_default" >/dev/null 2>&1 || true
  say "podman-compose down -v: no container or volume of $compose_project left"
fi
finish_phase

printf '\n==== test-image: PASSED ====\n'
printf '  %s\n' "${timings[@]}"
printf '  %-44s %5d s\n' "total" "$SECONDS"
