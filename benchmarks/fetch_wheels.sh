#!/usr/bin/env bash
# Here (a machine with PyPI): the wheels benchmarks/gpu.sh installs on the lent GPU machine (Python 3.12, x86-64),
# laid out for the device tool's 64 MiB a call: .whl/e taichi, .whl/f dill (split-bench, sim_throughput need only
# these two), .whl/a, .whl/c, .whl/d warp-lang in three parts (gpu.sh joins them), .whl/b the rest (Hydra and its
# joblib launcher, antlr4, trimesh, zarr 3.1 and its codecs, gymnasium), imageio-ffmpeg in two parts, .whl/g and
# .whl/b (its ffmpeg binary, 65 MiB: the machine has imageio and matplotlib but no encoder, and an evaluation that
# films refuses to start without one).  Carry [e, f], then [a], [c], [d], [b], [g] in back-to-back calls, each
# starting with `bash benchmarks/gpu.sh wheels` (docs/benchmarks.md).
# Usage: bash benchmarks/fetch_wheels.sh   (writes .whl/, which .gitignore leaves out)
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
plat=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
      --platform manylinux2014_x86_64 --platform manylinux1_x86_64)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${plat[@]}" \
  -d "$tmp" taichi==1.7.4 dill warp-lang==1.19.0 hydra-core==1.3.2 omegaconf==2.3.0 hydra-joblib-launcher trimesh \
  "zarr>=3,<3.2" numcodecs donfig crc32c google-crc32c gymnasium farama-notifications imageio-ffmpeg
python3 -m pip wheel -q --no-deps -w "$tmp" antlr4-python3-runtime==4.9.3  # a source release only: built here
rm -rf .whl && mkdir -p .whl/{a,b,c,d,e,f,g}
mv "$tmp"/taichi-*.whl .whl/e/ && mv "$tmp"/dill-*.whl .whl/f/
split -b 48M -d -a 2 "$tmp"/imageio_ffmpeg-*.whl "$tmp"/ffmpeg.part && rm "$tmp"/imageio_ffmpeg-*.whl
mv "$tmp"/ffmpeg.part00 .whl/g/ && mv "$tmp"/ffmpeg.part01 .whl/b/
split -b 50M -d -a 2 "$tmp"/warp_lang-*.whl "$tmp"/warp.part && rm "$tmp"/warp_lang-*.whl
mv "$tmp"/warp.part00 .whl/a/ && mv "$tmp"/warp.part01 .whl/c/ && mv "$tmp"/warp.part02 .whl/d/
mv "$tmp"/*.whl .whl/b/
du -sh .whl/*
