# Multi-stage build of PoseMatch (CPU, flex backend): the gRPC and HTTP service by default, the
# CLI too. This is the file deploy/test-containers.sh builds and runs end to end.
#   docker build -t posematch .
#   docker run --rm -p 50051:50051 -p 9090:9090 -v posematch-templates:/data/templates posematch
#   (embedded default weights; other weights: -v "$PWD/w.pth:/models/weights:ro" -e POSEMATCH__WEIGHTS=/models/weights)
#   docker run --rm -v "$PWD/data:/work" posematch match --template /work/t.png --image /work/s.png ...
# Base images are build arguments: without a registry, deploy/base-images/build.sh makes both
# from Debian's packages (deploy/README.md, "Without a registry").
ARG RUST_IMAGE=rust:1.95-slim-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

# The package's targets as empty programs, so that the dependency layer below depends on the
# manifest and the targets' names only: editing code does not rebuild burn and tonic, and a new
# bench or example needs no change here (`cargo metadata` checks the manifest finds them all).
FROM ${RUST_IMAGE} AS skeleton
WORKDIR /src
COPY . .
RUN mkdir -p /skeleton \
 && cp Cargo.toml Cargo.lock build.rs /skeleton/ \
 && for target in src/main.rs src/lib.rs benches/*.rs benches/*/main.rs examples/*.rs examples/*/main.rs; do \
      if [ -f "$target" ]; then \
        mkdir -p "/skeleton/$(dirname "$target")" && echo 'fn main() {}' > "/skeleton/$target" || exit 1; \
      fi; \
    done \
 && cd /skeleton && cargo metadata --no-deps --offline --format-version 1 > /dev/null

FROM ${RUST_IMAGE} AS build
WORKDIR /src
COPY --from=skeleton /skeleton ./
COPY proto proto
RUN cargo build --release --locked --bin posematch \
 && rm -rf src benches examples
COPY src src
COPY benches benches
# The default weights and settings are compiled into the binary (include_bytes!, include_str!).
COPY models models
COPY deploy/posematch.toml deploy/posematch.toml
RUN touch src/main.rs src/lib.rs && cargo build --release --locked --bin posematch

FROM ${RUNTIME_IMAGE}
# A fixed uid and gid (10001:10001): files mounted into the container (TLS key, token file,
# a batch job's folder) are made readable with `chown 10001:10001` or `chgrp 10001`.
RUN groupadd --system --gid 10001 posematch \
 && useradd --system --uid 10001 --gid 10001 --create-home --home-dir /home/posematch posematch \
 && mkdir -p /data/templates /etc/posematch && chown -R 10001:10001 /data
COPY --from=build /src/target/release/posematch /usr/local/bin/posematch
COPY deploy/posematch.toml /etc/posematch/posematch.toml
COPY LICENSE* README.md /usr/share/doc/posematch/
# Numeric, so that Kubernetes' runAsNonRoot can check it.
USER 10001:10001
WORKDIR /data
# Templates are kept in /data/templates: mount a named volume there (docker run -v
# posematch-templates:/data/templates) to keep them across containers. No VOLUME instruction:
# it would leave an anonymous volume behind for every container that stores templates
# elsewhere (the compose replicas keep theirs in PostgreSQL).
EXPOSE 50051 9090
ENV POSEMATCH__TEMPLATE_DIR=/data/templates
# SERVING only once the model is loaded (standard grpc.health.v1, asked by the binary itself).
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
  CMD ["posematch", "health", "--addr", "127.0.0.1:50051"]
# SIGTERM drains in-flight requests (shutdown_grace_seconds) before exiting.
STOPSIGNAL SIGTERM
ENTRYPOINT ["posematch"]
CMD ["serve", "--config", "/etc/posematch/posematch.toml"]
