# Multi-stage build of the `posematch` binary (CPU, flex backend).
#   docker build -t posematch .
#   docker run --rm -v "$PWD/data:/data" posematch match --template /data/t.png --image /data/s.png --weights /data/weights.bpk
FROM rust:1.95-slim-bookworm AS build
WORKDIR /src
# Dependencies first, so that source edits do not rebuild burn.
COPY Cargo.toml Cargo.lock ./
RUN mkdir -p src benches \
 && echo 'fn main() {}' > src/main.rs && echo '' > src/lib.rs && echo 'fn main() {}' > benches/network.rs \
 && cargo build --release --locked --bin posematch \
 && rm -rf src benches
COPY src src
COPY benches benches
COPY proto proto
RUN touch src/main.rs src/lib.rs && cargo build --release --locked --bin posematch

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --create-home --home-dir /home/posematch posematch \
 && mkdir -p /data && chown posematch /data
COPY --from=build /src/target/release/posematch /usr/local/bin/posematch
COPY LICENSE* README.md /usr/share/doc/posematch/
USER posematch
WORKDIR /data
ENTRYPOINT ["posematch"]
CMD ["--help"]
