#!/bin/sh
# placedb-init-secrets [DIR]: makes the secrets a TLS + tokens deployment needs, once.
#
# In the image as /usr/local/bin/placedb-init-secrets; the Compose stack runs it as the one-shot
# service `placedb-secrets` (as root, DIR = the `placedb-secrets` volume at /run/secrets) before
# placedb and Prometheus start. For Kubernetes, run it once on your machine and turn the files
# into Secrets (deploy/README.md). At first run it writes, under DIR (default /run/secrets):
#
#   ca/ca.key, ca/ca.crt          a private CA (EC P-256, 10 years); only root can read the key
#   placedb/tls.key, tls.crt      the server's key and certificate signed by it (825 days), with
#                                 the subject alternative names of PLACEDB_TLS_SERVER_NAMES
#   placedb/ca.crt                the CA certificate (the HEALTHCHECK and clients verify with it)
#   engines/tls.key, tls.crt, ca.crt   the same key, certificate and CA for nats-server and etcd
#                                 in compose-cluster.yaml (cluster.internal_tls: every hop is
#                                 mutual TLS with this one certificate, so it allows serverAuth
#                                 and clientAuth)
#   placedb/tokens.yaml           principals `admin` (admin) and `prometheus` (metrics): token
#                                 hashes only, written by `placedb-server tokens add`
#   prometheus/ca.crt             for Prometheus' tls_config.ca_file
#   prometheus/metrics.password   the `prometheus` token, for basic_auth.password_file
#
# and prints the admin token once, on stdout (the service's log). placedb/ belongs to the
# image's user (PLACEDB_UID, 10001) and prometheus/ to Prometheus' (PROMETHEUS_UID, 65534,
# `nobody` in prom/prometheus), each mode 0700, so that neither reads the other's secrets.
# When placedb/tokens.yaml exists it changes nothing and prints no token: later starts are no-ops.
#
# Environment:
#   PLACEDB_TLS_SERVER_NAMES  comma-separated DNS names and IP addresses clients dial
#                             (default placedb,localhost,127.0.0.1; the HEALTHCHECK dials
#                             127.0.0.1). Add the host name robots use.
#   PLACEDB_UID, PROMETHEUS_UID   owners of placedb/ and prometheus/ (chown only as root)
#   ENGINES_UID                   owner of engines/ (1001: bitnami/etcd's user; nats runs as root)
set -eu

dir="${1:-/run/secrets}"
names="${PLACEDB_TLS_SERVER_NAMES:-placedb,localhost,127.0.0.1}"
placedb_uid="${PLACEDB_UID:-10001}"
prometheus_uid="${PROMETHEUS_UID:-65534}"
engines_uid="${ENGINES_UID:-1001}"
server="${PLACEDB_SERVER_BINARY:-/usr/local/bin/placedb-server}"

say() { printf 'placedb-init-secrets: %s\n' "$*"; }
die() {
  printf 'placedb-init-secrets: FAILED: %s\n' "$*" >&2
  exit 1
}

if [ -e "$dir/placedb/tokens.yaml" ]; then
  say "$dir/placedb/tokens.yaml exists: the secrets are made already; nothing changed"
  exit 0
fi
for d in ca placedb prometheus engines; do
  [ ! -e "$dir/$d" ] ||
    die "$dir/$d exists but $dir/placedb/tokens.yaml does not (an interrupted run?): remove $dir/ca, $dir/placedb, $dir/prometheus and $dir/engines and start again"
done
command -v openssl >/dev/null || die "openssl is not installed"
[ -x "$server" ] || die "$server is missing"

umask 077
mkdir -p "$dir"
tmp="$(mktemp -d "$dir/.init.XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
mkdir "$tmp/ca" "$tmp/placedb" "$tmp/prometheus" "$tmp/engines"

# subjectAltName from the list: IPv4/IPv6 literals as IP:, the rest as DNS:.
san=""
old_ifs="$IFS"
IFS=,
for n in $names; do
  [ -n "$n" ] || continue
  case "$n" in
    *[!0-9.]* | "") case "$n" in *:*) entry="IP:$n" ;; *) entry="DNS:$n" ;; esac ;;
    *) entry="IP:$n" ;;
  esac
  san="${san:+$san,}$entry"
done
IFS="$old_ifs"
[ -n "$san" ] || die "PLACEDB_TLS_SERVER_NAMES is empty"

openssl req -x509 -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 \
  -keyout "$tmp/ca/ca.key" -out "$tmp/ca/ca.crt" -days 3650 -subj "/CN=placedb CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
  2>"$tmp/openssl.log" || { cat "$tmp/openssl.log" >&2; die "openssl: the CA"; }
openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 \
  -keyout "$tmp/placedb/tls.key" -out "$tmp/server.csr" -subj "/CN=placedb" \
  2>"$tmp/openssl.log" || { cat "$tmp/openssl.log" >&2; die "openssl: the server key"; }
printf '%s\n' "basicConstraints=CA:FALSE" "keyUsage=critical,digitalSignature" \
  "extendedKeyUsage=serverAuth,clientAuth" "subjectAltName=$san" >"$tmp/server.ext"
openssl x509 -req -in "$tmp/server.csr" -CA "$tmp/ca/ca.crt" -CAkey "$tmp/ca/ca.key" \
  -set_serial "0x$(openssl rand -hex 16)" -days 825 -sha256 -extfile "$tmp/server.ext" \
  -out "$tmp/placedb/tls.crt" 2>"$tmp/openssl.log" ||
  { cat "$tmp/openssl.log" >&2; die "openssl: the server certificate"; }
cp "$tmp/ca/ca.crt" "$tmp/placedb/ca.crt"
cp "$tmp/ca/ca.crt" "$tmp/prometheus/ca.crt"
cp "$tmp/ca/ca.crt" "$tmp/placedb/tls.crt" "$tmp/placedb/tls.key" "$tmp/engines/"
say "server certificate for $san, signed by a new CA (valid 825 days)"

# The tokens: `tokens add` prints the token once and stores only its SHA-256.
new_token() {  # NAME ROLE -> the token on stdout
  out="$("$server" tokens add "$1" --tokens-file "$tmp/placedb/tokens.yaml" --role "$2" 2>&1)" ||
    { printf '%s\n' "$out" >&2; die "placedb-server tokens add $1 --role $2"; }
  token="$(printf '%s\n' "$out" | grep -oE 'pdb_[A-Za-z0-9_-]{43}' | head -n 1)"
  [ -n "$token" ] || { printf '%s\n' "$out" >&2; die "no token in the output of tokens add $1"; }
  printf '%s' "$token"
}
admin_token="$(new_token admin admin)"
new_token prometheus metrics >"$tmp/prometheus/metrics.password"

chmod 0644 "$tmp/ca/ca.crt" "$tmp/placedb/tls.crt" "$tmp/placedb/ca.crt"
chmod 0600 "$tmp/ca/ca.key" "$tmp/placedb/tls.key" "$tmp/placedb/tokens.yaml"
chmod 0400 "$tmp/prometheus/ca.crt" "$tmp/prometheus/metrics.password"
chmod 0644 "$tmp/engines/ca.crt" "$tmp/engines/tls.crt"
chmod 0600 "$tmp/engines/tls.key"
chmod 0700 "$tmp/ca" "$tmp/placedb" "$tmp/prometheus" "$tmp/engines"
chmod 0755 "$dir"
if [ "$(id -u)" = 0 ]; then
  chown -R "$placedb_uid:$placedb_uid" "$tmp/placedb"
  chown -R "$prometheus_uid:$prometheus_uid" "$tmp/prometheus"
  chown -R "$engines_uid:$engines_uid" "$tmp/engines"
else
  say "not root: $dir/placedb and $dir/prometheus stay owned by $(id -un)"
fi
# placedb/ last: its tokens.yaml marks the work as done.
mv "$tmp/ca" "$dir/ca"
mv "$tmp/prometheus" "$dir/prometheus"
mv "$tmp/engines" "$dir/engines"
mv "$tmp/placedb" "$dir/placedb"

say "wrote $dir/placedb (server key, certificate, CA certificate, tokens.yaml),"
say "  $dir/prometheus (CA certificate, metrics password) and $dir/ca (the CA's key)"
say "the admin token, shown this once (only its SHA-256 is stored; keep it safe):"
printf '%s\n' "$admin_token"
