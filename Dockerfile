# placedb: the place-recognition database service (docs/service.md, deploy/README.md).
#
#   docker build -t placedb .                          # detector model from var/models if there
#   docker build --build-arg MODELS= -t placedb .      # no detector model: detection off
#   docker build --build-arg MODELS=models -t placedb .    # models from ./models in the context
#   docker run --rm --user 0 -v placedb-secrets:/run/secrets --entrypoint placedb-init-secrets \
#       placedb                                       # once: CA, certificate, tokens; prints the
#                                                     # admin token
#   docker run -p 50051:50051 -p 9464:9464 -v placedb-secrets:/run/secrets:ro \
#       -v placedb-data:/var/lib/placedb placedb
#
# The server runs with TLS (gRPC and /metrics) and a tokens file, read from /run/secrets/placedb
# (PLACEDB_TLS_CERT_FILE, PLACEDB_TLS_KEY_FILE, PLACEDB_TOKENS_FILE below; a mounted Secret or the
# volume placedb-init-secrets fills): without them it refuses to start. deploy/README.md.
#
# Stage "runtime-base" is bookworm-slim plus openssl (placedb-init-secrets). Stage "build"
# installs the Debian packages tools/setup.sh lists, builds Release (the CLI without OpenCV's
# image and video I/O: JPEG and PNG only, -DPLACEDB_CLI_OPENCV_IO=OFF), trains the default
# vocabulary on Debian's sample images (opencv-doc, darknet) and copies the shared libraries the
# binaries load (their ldd closure, minus what runtime-base has) out of the Debian packages.
# Stage "runtime" is runtime-base with those libraries, the binaries, the vocabulary, the optional
# detector model and a non-root user: no lib package is installed there, so none of their
# dependencies (Mesa, LLVM, GDAL, FFmpeg, ... through Debian's OpenCV) comes with them.
#
# Build arguments:
#   BASE_IMAGE  base of both stages (debian:bookworm-slim; deploy/test-image.sh substitutes a
#               locally debootstrapped copy)
#   JOBS        parallel compile jobs (2)
#   MODELS      a directory of the build context holding yolox_nano.onnx and/or
#               yolo-fastest-1.1-xl.{cfg,weights} (tools/install_models.sh puts them in var/models);
#               empty or missing: the image has no model and server-side detection is off
#   REQUIRE_CLI 1 (default): fail when the `placedb` CLI target is missing (the HEALTHCHECK uses
#               it); 0: build without it (the HEALTHCHECK then reports unhealthy)
ARG BASE_IMAGE=debian:bookworm-slim

# ---------------------------------------------------------------------------------------------
# The runtime's Debian packages: the base and openssl (placedb-init-secrets makes the CA and the
# server certificate with it). The build stage copies only the libraries this stage lacks.
FROM ${BASE_IMAGE} AS runtime-base
ARG DEBIAN_FRONTEND=noninteractive
RUN apt-get update -q \
 && apt-get install -y -q --no-install-recommends openssl \
 && rm -rf /var/lib/apt/lists/*

# ---------------------------------------------------------------------------------------------
FROM ${BASE_IMAGE} AS build
ARG DEBIAN_FRONTEND=noninteractive

# bookworm-slim drops /usr/share/doc/* at install time (dpkg path-exclude); the default
# vocabulary is trained on opencv-doc's sample images, which live there. Re-include them (the
# last matching dpkg filter wins; files in dpkg.cfg.d are read in name order).
RUN printf 'path-include=/usr/share/doc/opencv-doc/*\n' > /etc/dpkg/dpkg.cfg.d/zz-placedb-build

# The packages first (tools/setup.sh --deps is the single list), so that source edits reuse this
# layer.
COPY tools/setup.sh /src/tools/setup.sh
RUN /src/tools/setup.sh --deps && rm -rf /var/lib/apt/lists/*

# Declared after the packages so that changing them does not invalidate that layer.
ARG JOBS=2
ARG MODELS=var/models
ARG REQUIRE_CLI=1
COPY . /src
WORKDIR /src
# The CLI reads JPEG and PNG only (PLACEDB_CLI_OPENCV_IO=OFF): OpenCV's imgcodecs and videoio
# would bring GDAL, PROJ, HDF5, Poppler, FFmpeg and GStreamer (~230 MB); it refuses videos and
# other image formats with a message saying so.
RUN cmake -S . -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release \
      -DPLACEDB_BUILD_TESTS=OFF -DPLACEDB_BUILD_BENCH=OFF -DPLACEDB_CLI_OPENCV_IO=OFF \
 && targets="placedb-server placedb-vocab placedb-sift-vocab" \
 && if ninja -C /build -t targets all | grep -q '^placedb: '; then \
      targets="$targets placedb"; \
    elif [ "$REQUIRE_CLI" = 1 ]; then \
      echo "Dockerfile: the placedb CLI target is missing (client/); the HEALTHCHECK needs it." \
           "Build with --build-arg REQUIRE_CLI=0 to go on without it." >&2; exit 1; \
    else \
      echo "Dockerfile: WARNING: no placedb CLI target: the image's HEALTHCHECK will fail" >&2; \
    fi \
 && cmake --build /build -j "$JOBS" --target $targets \
 && mkdir -p /out/usr/local/bin \
 && for t in $targets; do \
      bin=$(find /build -type f -name "$t" -perm -u+x | head -n 1); \
      [ -n "$bin" ] || { echo "Dockerfile: built $t but cannot find it" >&2; exit 1; }; \
      install -s -m 755 "$bin" /out/usr/local/bin/"$t"; \
    done

# The default vocabulary (Debian sample images only; a fixed seed, so reproducible). The
# vocabulary tools are build-time only: they read images and videos through OpenCV's imgcodecs
# and videoio, which the runtime does not carry.
RUN tools/build_default_vocabulary.sh /out/usr/local/bin/placedb-vocab \
      /out/usr/share/placedb/vocabulary/default.pdbv \
 && /out/usr/local/bin/placedb-sift-vocab --out /out/usr/share/placedb/vocabulary/sift.pdbfv \
 && rm /out/usr/local/bin/placedb-sift-vocab /out/usr/local/bin/placedb-vocab

# The detector model, when the context has one; the image's config points at it.
RUN mkdir -p /out/usr/share/placedb/models /out/etc/placedb \
 && if [ -n "$MODELS" ] && [ -d "/src/$MODELS" ]; then \
      for f in yolox_nano.onnx yolo-fastest-1.1-xl.cfg yolo-fastest-1.1-xl.weights; do \
        if [ -f "/src/$MODELS/$f" ]; then \
          install -m 644 "/src/$MODELS/$f" /out/usr/share/placedb/models/; \
          echo "Dockerfile: detector model $f included"; \
        fi; \
      done; \
    fi \
 && cp deploy/placedb.yaml /out/etc/placedb/placedb.yaml \
 && if [ -f /out/usr/share/placedb/models/yolox_nano.onnx ]; then \
      sed -i 's|^  model: ""|  model: /usr/share/placedb/models/yolox_nano.onnx|' \
        /out/etc/placedb/placedb.yaml; \
      grep -q '^  model: /usr/share/placedb/models/yolox_nano.onnx' /out/etc/placedb/placedb.yaml; \
    else \
      echo "Dockerfile: no detector model in '$MODELS': server-side detection will be off"; \
    fi

# The shared libraries the binaries load (ldd: the whole closure) that runtime-base does not
# have, copied from the packages installed here with their copyright files and a manifest
# (/usr/share/doc/placedb/runtime-libraries.txt: package, version, file). A build with
# -DPLACEDB_ALLOCATOR=jemalloc or mimalloc gets libjemalloc / libmimalloc this way.
COPY --from=runtime-base /var/lib/dpkg/status /tmp/runtime-dpkg-status
RUN deploy/docker/runtime-libraries.sh /tmp/runtime-dpkg-status /out /out/usr/local/bin/*

# ---------------------------------------------------------------------------------------------
FROM runtime-base AS runtime
COPY --from=build /out/usr /usr
COPY --from=build /out/etc/placedb /etc/placedb
# The secrets' one-shot maker (Compose's placedb-secrets service) and the health check.
COPY deploy/docker/init-secrets.sh /usr/local/bin/placedb-init-secrets
COPY deploy/docker/healthcheck.sh /usr/local/bin/placedb-healthcheck
# Every binary resolves every library (a missing one fails the build, not a pod).
RUN chmod 755 /usr/local/bin/placedb-init-secrets /usr/local/bin/placedb-healthcheck \
 && ldconfig \
 && for b in /usr/local/bin/placedb*; do \
      if ldd "$b" | grep 'not found'; then echo "Dockerfile: $b misses libraries" >&2; exit 1; fi; \
    done \
 && groupadd --system --gid 10001 placedb \
 && useradd --system --uid 10001 --gid placedb --home-dir /var/lib/placedb --no-create-home \
      --shell /usr/sbin/nologin placedb \
 && install -d -o placedb -g placedb -m 750 /var/lib/placedb

# Configuration: the file (PLACEDB_CONFIG; mount your own over it), then PLACEDB_* environment,
# then flags (arguments after the image name). docs/service.md lists every key.
ENV PLACEDB_CONFIG=/etc/placedb/placedb.yaml
# Metrics on every interface, for a Prometheus in another container (the server's default is
# loopback). An environment variable rather than only the config file's key, so that a mounted
# config without metrics_listen still exposes them.
ENV PLACEDB_METRICS_LISTEN=0.0.0.0:9464
# TLS on gRPC and /metrics, and the tokens file, from mounted secrets (a Kubernetes Secret, or
# the volume placedb-init-secrets fills). The server refuses to start without them; it listens
# on 0.0.0.0 (the config file) because it authenticates callers. Mutual TLS: also set
# PLACEDB_TLS_CLIENT_CA_FILE. Point these elsewhere to use other files.
ENV PLACEDB_TLS_CERT_FILE=/run/secrets/placedb/tls.crt \
    PLACEDB_TLS_KEY_FILE=/run/secrets/placedb/tls.key \
    PLACEDB_TOKENS_FILE=/run/secrets/placedb/tokens.yaml \
    PLACEDB_METRICS_TLS=true
USER placedb:placedb
WORKDIR /var/lib/placedb
VOLUME ["/var/lib/placedb"]
EXPOSE 50051 9464
# The standard gRPC health service over TLS (placedb-healthcheck: `placedb --tls health` on
# 127.0.0.1, trusting ca.crt beside the certificate; 0 SERVING, else 1). The port follows
# PLACEDB_LISTEN (default 50051): a server moved to another port by the config file or --listen
# needs PLACEDB_LISTEN to match.
HEALTHCHECK --interval=15s --timeout=5s --start-period=60s --retries=3 \
  CMD ["/usr/local/bin/placedb-healthcheck"]
STOPSIGNAL SIGTERM
ENTRYPOINT ["/usr/local/bin/placedb-server"]
CMD []
