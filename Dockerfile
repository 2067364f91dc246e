# ctrecon service image: multi-stage build, non-root runtime user, health check.
#   docker build -t ctrecon .
#   docker run -p 8080:8080 -e CTRECON_API_TOKENS=change-me-please-0123 -v ctrecon-data:/data ctrecon

FROM rust:1.95-bookworm AS build
WORKDIR /src
# Dependencies first, so that source edits do not rebuild them.
COPY Cargo.toml Cargo.lock build.rs ./
COPY migrations migrations
RUN mkdir -p src benches && echo 'fn main() {}' > src/main.rs && touch src/lib.rs \
    && cargo build --release --locked --bin ctrecon 2>/dev/null || true
COPY . .
RUN touch src/main.rs src/lib.rs && cargo build --release --locked --bin ctrecon \
    && strip target/release/ctrecon

FROM debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends ca-certificates curl \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --home-dir /data --shell /usr/sbin/nologin ctrecon \
    && mkdir -p /data && chown ctrecon:ctrecon /data
COPY --from=build /src/target/release/ctrecon /usr/local/bin/ctrecon
USER ctrecon
WORKDIR /data
ENV CTRECON_DATA_DIR=/data \
    CTRECON_BIND=0.0.0.0:8080 \
    CTRECON_LOG_FORMAT=json
EXPOSE 8080
VOLUME ["/data"]
# Without CTRECON_API_TOKENS the service refuses a non-loopback bind; set tokens (or, on a private
# network only, CTRECON_ALLOW_INSECURE=true).
HEALTHCHECK --interval=30s --timeout=3s --start-period=10s --retries=3 \
    CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["ctrecon", "serve"]
