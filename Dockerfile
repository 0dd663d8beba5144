# The modbus-harness binary in a small image:
#   docker build -t modbus-harness .
#   docker run --rm --network host -v "$PWD/out:/out" modbus-harness \
#     run --target tcp://127.0.0.1:5020 --profile mdrive --report /out
# The corpus (profiles, golden frames, requirements) is built into the binary; mount a directory and pass
# --corpus or --profile ./my.toml for your own.
FROM rust:1-slim-bookworm AS build
WORKDIR /src
COPY . .
RUN cargo build --release --locked -p modbus-harness \
 && strip target/release/modbus-harness

FROM debian:bookworm-slim
RUN useradd --system --no-create-home harness
COPY --from=build /src/target/release/modbus-harness /usr/local/bin/modbus-harness
USER harness
WORKDIR /work
ENTRYPOINT ["modbus-harness"]
CMD ["--help"]
