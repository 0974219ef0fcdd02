#!/usr/bin/env bash
# The GPU check (docs/benchmarks.md, "GPU check"): on an offline CUDA machine with torch and nvcc, in about
# 9 minutes, install the wheels scripts/prepare_gpu_wheels.sh prepared, build gsplat for this GPU's architecture
# only, run `pytest -m cuda`, `vid2sim bench speed --device cuda`, and a full-preset `reconstruct` + `evaluate` of
# the scene prepared with the wheels; write one JSON of figures.
#
# Usage: scripts/gpu_check.sh [RESULT_DIR]        (in the repository's root; RESULT_DIR default: gpu_check/)
#   RESULT_DIR/gpu_check.json   the figures: the GPU, each phase's seconds and exit status, pytest's counts,
#                               bench speed's figures, the full reconstruction's seconds and its evaluation
#   RESULT_DIR/*.log            each phase's output
# Environment: GPU_CHECK_BUDGET_S (default 530): the whole run's seconds; each phase is stopped at what is left of
#   them (its status then 124, recorded in the JSON). WHEELS (default .whl), SCENE (default .gpu_check/scene).
#   GPU_CHECK_PHASES (default all: install build_gsplat pytest_cuda bench_speed reconstruct_full evaluate_full): the
#   phases to run, to repeat some of them on a warm machine. GPU_CHECK_BENCH (default training joint render
#   physics): bench speed's sections, in this order.
# Exit status: 0 when every phase succeeded, else 1 (the JSON is written either way).
set -uo pipefail
cd "$(dirname "$0")/.."

RESULT=${1:-gpu_check}
WHEELS=${WHEELS:-.whl}
SCENE=${SCENE:-.gpu_check/scene}
BUDGET=${GPU_CHECK_BUDGET_S:-530}
SITE=/tmp/vid2sim-gpu-site
START=$(date +%s)
mkdir -p "$RESULT"
PHASES="$RESULT/phases.tsv"
: >"$PHASES"

if ! ls "$WHEELS"/*.whl >/dev/null 2>&1; then
  echo "gpu_check: no wheels in $WHEELS; run scripts/prepare_gpu_wheels.sh where there is a package index" >&2
  exit 2
fi
if [[ ! -f "$SCENE/scene.json" ]]; then
  echo "gpu_check: no scene at $SCENE; scripts/prepare_gpu_wheels.sh makes it" >&2
  exit 2
fi

# phase NAME CAP_S COMMAND...: run COMMAND with its output in RESULT/NAME.log, stopped after CAP_S seconds or at
# the end of the budget, whichever comes first; one line "NAME<TAB>status<TAB>seconds" in phases.tsv
ALL_PHASES="install build_gsplat pytest_cuda bench_speed reconstruct_full evaluate_full"
WANTED=" ${GPU_CHECK_PHASES:-$ALL_PHASES} "
phase() {
  local name=$1 cap=$2
  shift 2
  [[ $WANTED == *" $name "* ]] || return 0
  local left=$((BUDGET - ($(date +%s) - START)))
  ((left < cap)) && cap=$left
  if ((cap < 5)); then
    printf '%s\t%s\t%s\n' "$name" skipped 0 >>"$PHASES"
    echo "== $name: skipped (the budget is spent)"
    return 1
  fi
  echo "== $name (at most ${cap} s)"
  local t0 status ms
  t0=$(date +%s%N)
  # through bash, so that COMMAND may be one of this script's functions (exported below)
  timeout --kill-after=10 "$cap" bash -c '"$@"' bash "$@" >"$RESULT/$name.log" 2>&1
  status=$?
  ms=$((($(date +%s%N) - t0) / 1000000))
  printf '%s\t%s\t%d.%d\n' "$name" "$status" $((ms / 1000)) $((ms % 1000 / 100)) >>"$PHASES"
  tail -n 3 "$RESULT/$name.log"
  return "$status"
}

install_wheels() {
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" \
    "$WHEELS"/*.whl
}
export RESULT WHEELS SITE
export -f install_wheels
phase install 90 install_wheels
export PYTHONPATH="$PWD/src:$SITE${PYTHONPATH:+:$PYTHONPATH}"
export PATH="$SITE/bin:$PATH"

# gsplat 1.5.3 compiles its CUDA code on first import; only for this GPU's architecture (sm_90 on an H200),
# with every core, in a build folder the later phases find
TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
export TORCH_CUDA_ARCH_LIST
export TORCH_EXTENSIONS_DIR=/tmp/vid2sim-torch-extensions
export MAX_JOBS=$(nproc)
phase build_gsplat 300 python3 -c "
from gsplat.cuda._backend import _C
assert _C is not None, 'gsplat did not compile (no CUDA toolkit found?)'
print('gsplat built for sm_' + '$TORCH_CUDA_ARCH_LIST'.replace('.', ''))"

# the GPU tests spread test by test over 8 workers (--dist load: test_cuda_commands.py's commands run side by side;
# the module fixture is then built by each worker that needs it), each result on its own line (-v), so that a run cut
# short by the budget still says which passed
phase pytest_cuda 220 python3 -m pytest -m cuda -p no:cacheprovider -v -rfEs -n 8 --dist load \
  --junitxml="$RESULT/pytest_cuda.xml"
# bench speed a section at a time, each into its own JSON, so that one cut short by the budget loses only itself
bench_sections() {
  local section
  for section in ${GPU_CHECK_BENCH:-training joint render physics}; do
    python3 -m vid2sim bench speed --device cuda --only "$section" --json >"$RESULT/bench_$section.json" || return
  done
}
export -f bench_sections
phase bench_speed 120 bench_sections
# the full reconstruction gets what is left but the evaluation's share (70 s at full size on an H200); not --quiet, so its log has each stage
left=$((BUDGET - ($(date +%s) - START) - 90))
phase reconstruct_full "$left" python3 -m vid2sim reconstruct "$SCENE" "$RESULT/asset" --preset full --device cuda \
  --no-report --overwrite
phase evaluate_full 90 python3 -m vid2sim evaluate "$RESULT/asset" "$SCENE" --out "$RESULT/evaluation.json" \
  --device cuda --no-report --quiet

python3 - "$RESULT" "$SCENE" "$BUDGET" "$WANTED" <<'PY'
import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import torch

result, scene, budget, wanted = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3]), sys.argv[4].split()


def read_json(path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


phases = {}
for line in (result / "phases.tsv").read_text().splitlines():
    name, status, seconds = line.split("\t")
    phases[name] = {"status": int(status) if status.lstrip("-").isdigit() else status, "seconds": float(seconds)}
figures = {
    "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    "torch": torch.__version__,
    "cuda": torch.version.cuda,
    "arch": f"sm_{''.join(map(str, torch.cuda.get_device_capability(0)))}" if torch.cuda.is_available() else None,
    "budget_s": budget,
    "total_s": round(sum(p["seconds"] for p in phases.values()), 1),
    "phases": phases,
    "ok": all(p["status"] == 0 for p in phases.values()) and len(phases) == len(wanted),
}
try:
    suite = ET.parse(result / "pytest_cuda.xml").getroot()
    suite = suite.find("testsuite") if suite.tag == "testsuites" else suite
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    counts["failed"] = [f"{case.get('classname')}::{case.get('name')}" for case in suite.iter("testcase")
                        if case.find("failure") is not None or case.find("error") is not None]
    figures["pytest_cuda"] = counts
except (OSError, ET.ParseError):
    figures["pytest_cuda"] = None
bench = {}
for path in sorted(result.glob("bench_*.json")):  # the sections bench_sections wrote
    bench.update(read_json(path) or {})
figures["bench_speed"] = bench or None
material = read_json(result / "asset" / "material.json")
evaluation = read_json(result / "evaluation.json")
full = {"scene": str(scene), "preset": "full", "seconds": phases.get("reconstruct_full", {}).get("seconds")}
if material:
    full["E"], full["nu"] = material.get("E"), material.get("nu")
if evaluation:
    full["psnr"] = {k: evaluation[k]["psnr"] for k in ("dynamic", "future", "novel_views") if k in evaluation}
    found = evaluation.get("material", {})
    full["abs_error_log10_E"], full["abs_error_nu"] = found.get("abs_error_log10_E"), found.get("abs_error_nu")
    full["chamfer"] = evaluation.get("chamfer")
    full["evaluate_seconds"] = phases.get("evaluate_full", {}).get("seconds")
figures["reconstruct_full"] = full
(result / "gpu_check.json").write_text(json.dumps(figures, indent=2) + "\n")
print(json.dumps({k: figures[k] for k in ("gpu", "total_s", "ok", "pytest_cuda")}, indent=2))
sys.exit(0 if figures["ok"] else 1)
PY
