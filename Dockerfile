# Multi-stage build of PoseMatch (CPU, flex backend): the gRPC service by default, the CLI too.
#   docker build -t posematch .
#   docker run --rm -p 50051:50051 -p 9090:9090 -v posematch-templates:/data/templates posematch
#   (embedded default weights; other weights: -v "$PWD/w.bpk:/models/w.bpk:ro" -e POSEMATCH__WEIGHTS=/models/w.bpk)
#   docker run --rm -v "$PWD/data:/work" posematch match --template /work/t.png --image /work/s.png ...
FROM rust:1.95-slim-bookworm AS build
WORKDIR /src
# Dependencies first, so that source edits do not rebuild burn and tonic.
COPY Cargo.toml Cargo.lock build.rs ./
COPY proto proto
RUN mkdir -p src benches \
 && echo 'fn main() {}' > src/main.rs && echo '' > src/lib.rs \
 && for b in network load templates verification frames store; do echo 'fn main() {}' > benches/$b.rs; done \
 && cargo build --release --locked --bin posematch \
 && rm -rf src benches
COPY src src
COPY benches benches
# The default weights and settings are compiled into the binary (include_bytes!, include_str!).
COPY models models
COPY deploy/posematch.toml deploy/posematch.toml
RUN touch src/main.rs src/lib.rs && cargo build --release --locked --bin posematch

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --create-home --home-dir /home/posematch posematch \
 && mkdir -p /data/templates /etc/posematch && chown -R posematch /data
COPY --from=build /src/target/release/posematch /usr/local/bin/posematch
COPY deploy/posematch.toml /etc/posematch/posematch.toml
COPY LICENSE* README.md /usr/share/doc/posematch/
USER posematch
WORKDIR /data
# Templates live on a volume: a restarted container keeps every registered template.
VOLUME ["/data/templates"]
EXPOSE 50051 9090
ENV POSEMATCH__TEMPLATE_DIR=/data/templates
# SERVING only once the model is loaded (standard grpc.health.v1, asked by the binary itself).
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=3 \
  CMD ["posematch", "health", "--addr", "127.0.0.1:50051"]
# SIGTERM drains in-flight requests (shutdown_grace_seconds) before exiting.
STOPSIGNAL SIGTERM
ENTRYPOINT ["posematch"]
CMD ["serve", "--config", "/etc/posematch/posematch.toml"]
