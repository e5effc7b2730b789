# Prometheus for deploy/test-image.sh --compose: Debian's `prometheus` package on the test's own
# debootstrapped base, standing in for prom/prometheus (no container registry is reachable where
# the test runs). What Compose relies on is the same: the entrypoint is the prometheus binary and
# Compose's `command:` gives its flags, it runs as nobody (65534: the owner of the secrets
# volume's prometheus/ directory, deploy/docker/init-secrets.sh), and /prometheus is its data
# directory. Debian bookworm ships Prometheus 2.42; compose.yaml pins 2.53.1 for real use.
ARG BASE_IMAGE=debian:bookworm-slim
FROM ${BASE_IMAGE}
ARG DEBIAN_FRONTEND=noninteractive
RUN apt-get update -q \
 && apt-get install -y -q --no-install-recommends prometheus \
 && rm -rf /var/lib/apt/lists/* \
 && install -d -o 65534 -g 65534 -m 755 /prometheus
USER 65534:65534
WORKDIR /prometheus
VOLUME ["/prometheus"]
EXPOSE 9090
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
