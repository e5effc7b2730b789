#!/bin/sh
# placedb-healthcheck [SERVICE]: the image's HEALTHCHECK and the Kubernetes exec probes.
#
# Asks the standard gRPC health service (no token needed) on 127.0.0.1 at the port of
# PLACEDB_LISTEN (default 50051) with the image's `placedb health`, over TLS when
# PLACEDB_TLS_CERT_FILE is set, trusting PLACEDB_HEALTHCHECK_CA_FILE (default: ca.crt beside the
# certificate; none there: the system's roots). The server certificate must name 127.0.0.1
# (an IP subject alternative name). With mutual TLS set PLACEDB_HEALTHCHECK_CERT_FILE and
# PLACEDB_HEALTHCHECK_KEY_FILE to a client certificate the server accepts.
# Exit 0 when SERVING; 1 otherwise (Docker reserves 2).
service="${1:-}"
listen="${PLACEDB_LISTEN:-:50051}"
port="${listen##*:}"

set -- --timeout 3
if [ -n "${PLACEDB_TLS_CERT_FILE:-}" ]; then
  set -- "$@" --tls
  ca="${PLACEDB_HEALTHCHECK_CA_FILE:-$(dirname "$PLACEDB_TLS_CERT_FILE")/ca.crt}"
  if [ -f "$ca" ]; then set -- "$@" --ca-cert "$ca"; fi
  if [ -n "${PLACEDB_HEALTHCHECK_CERT_FILE:-}" ]; then
    set -- "$@" --cert "$PLACEDB_HEALTHCHECK_CERT_FILE" --key "${PLACEDB_HEALTHCHECK_KEY_FILE:-}"
  fi
fi
set -- "$@" health --address "127.0.0.1:$port"
if [ -n "$service" ]; then set -- "$@" --service "$service"; fi
/usr/local/bin/placedb "$@" || exit 1
