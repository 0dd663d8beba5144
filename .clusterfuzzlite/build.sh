#!/bin/bash -eu
# ClusterFuzzLite / OSS-Fuzz build script (Rust conventions): build the cargo-fuzz targets with the sanitizer
# flags of the base image, then copy each binary to $OUT with its seed corpus (<target>_seed_corpus.zip) and
# the Modbus dictionary (<target>.dict).
cd "$SRC/modbus-harness"

# Release build, keeping debug assertions and overflow checks (cargo fuzz's default without -O).
cargo fuzz build -O --debug-assertions

release=fuzz/target/x86_64-unknown-linux-gnu/release
for target in $(cargo fuzz list); do
  cp "$release/$target" "$OUT/"
  cp fuzz/dict/modbus.dict "$OUT/$target.dict"
  (cd "fuzz/corpus/$target" && zip -q -r "$OUT/${target}_seed_corpus.zip" .)
done
