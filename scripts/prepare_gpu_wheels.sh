#!/usr/bin/env bash
# Prepare, on a machine with a package index, what scripts/gpu_check.sh needs on an offline GPU machine
# (docs/benchmarks.md, "GPU check"):
#
#   .whl/                 wheels of vid2sim's dependencies that the GPU machine's image lacks (CPython 3.12,
#                         manylinux x86-64; gsplat 1.5.3 is a pure-Python wheel whose CUDA code gpu_check.sh
#                         compiles there, for that GPU's architecture only)
#   .gpu_check/scene/     the scene the check reconstructs with the full preset: make-scene --preset full, seed 0
#                         (14 views at 448², 24 frames), as H.264 videos (6.5 MB, so that it travels with the wheels
#                         under a call's 64 MiB); made here (2.5 min on 2 cores) so that the GPU's minutes go to GPU work
#
# Usage: scripts/prepare_gpu_wheels.sh [--no-scene]    (run in the repository's root; both folders are git-ignored)
#
# The GPU image (docs/benchmarks.md) has torch, numpy, scipy, pyyaml, pillow, imageio, scikit-image, matplotlib,
# safetensors, tqdm, transformers, packaging, jaxtyping, rich, ninja, pytest and pytest-xdist; the list below is the
# rest of `pip install -e ".[test]"`, with the versions this project is tested with, less numba: its llvmlite wheel
# alone is 60 MB, more than a call carries beside the others, and on the GPU the renders are gsplat's (the few CPU
# renders there composite with tensor operations and warn that numba is missing).
set -euo pipefail
cd "$(dirname "$0")/.."

WHEELS=(
  gsplat==1.5.3 trimesh==5.2.0 imageio-ffmpeg==0.6.0 pymetis==2025.2.2 pytetwild==0.4.2 scikit-fem==12.0.2
  pygltflib==1.16.5 dataclasses-json==0.6.7 marshmallow==3.26.2 deprecated==1.3.1
)
PLATFORMS=(manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_24_x86_64 manylinux_2_17_x86_64
           manylinux2014_x86_64 manylinux1_x86_64)

mkdir -p .whl
args=(--no-deps --only-binary=:all: --python-version 3.12 --implementation cp --abi cp312 --abi abi3 --abi none
      -d .whl)
for p in "${PLATFORMS[@]}"; do args+=(--platform "$p"); done
args+=(--platform any)
python3 -m pip download "${args[@]}" "${WHEELS[@]}"
# one version of each package: two would stop the install there
dupes=$(ls .whl/*.whl | xargs -n1 basename | cut -d- -f1 | tr 'A-Z-' 'a-z_' | sort | uniq -d)
if [[ -n "$dupes" ]]; then
  echo "prepare_gpu_wheels: several versions of: $dupes (remove the older ones from .whl/)" >&2
  exit 1
fi
du -sh .whl

if [[ "${1:-}" != "--no-scene" && ! -f .gpu_check/scene/scene.json ]]; then
  mkdir -p .gpu_check
  PYTHONPATH=src${PYTHONPATH:+:$PYTHONPATH} python3 -m vid2sim make-scene .gpu_check/scene --preset full --seed 0 \
    --layout video --quiet
fi
du -sh .gpu_check 2>/dev/null || true
echo "ready: carry .whl and .gpu_check to the GPU machine and run scripts/gpu_check.sh there"
