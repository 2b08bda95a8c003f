#!/usr/bin/env bash
# The GPU benchmark in one go, on a machine with an NVIDIA GPU: install onnxruntime-gpu and what
# the benchmark lacks, check that sessions really get CUDA (the GPU tests), run
# benchmarks/gpu_suffix.py on the CPU, CUDA and TensorRT, and leave its JSON and log in $OUT.
#
# Two ways to get the packages:
# - A machine without network (the lent GPU machine: at most 64 MiB travels per call, and
#   onnxruntime-gpu alone is 256 MB): first, here, `python3 benchmarks/gpu_wheels.py pack`
#   (the gpu lock's versions) writes .gpu-wheels/part-1..N; then one call per part, each
#   carrying only its own part, back to back (a machine left idle is given back, and the parts
#   staged on it with it):
#       bash benchmarks/gpu_device_run.sh stage     # calls 1..N-1, carry [.gpu-wheels/part-K]
#       bash benchmarks/gpu_device_run.sh run       # call N, carry [.gpu-wheels/part-N]
#   The parts are installed into one folder ($EF_GPU_SITE) put first on PYTHONPATH, over the
#   image's own Python, whose PyTorch brings the CUDA 13 and cuDNN 9 libraries onnxruntime-gpu
#   loads (a venv of its own would not see them).
# - A machine with network and no parts staged: a venv (.venv-gpu) from requirements/gpu.lock
#   (the `gpu` extra's lock). Until that lock exists: the dev lock, then the CPU onnxruntime
#   swapped for the newest onnxruntime-gpu (both install the module `onnxruntime`).
#
# Environment: OUT (results; the device tool sets it), GPU_BENCH_ARGS (more options for
# gpu_suffix.py, e.g. "--quick"), GPU_BENCH_TIMEOUT_S (default 420), EF_GPU_STAGE, EF_GPU_SITE.
set -euo pipefail
cd "$(dirname "$0")/.."
MODE="${1:-run}"
STAGE_DIR="${EF_GPU_STAGE:-/tmp/ef-gpu/parts}"
SITE="${EF_GPU_SITE:-/tmp/ef-gpu/site}"
OUT="${OUT:-$PWD/out/gpu}"
BENCH_TIMEOUT_S="${GPU_BENCH_TIMEOUT_S:-420}"
PY=python3
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1

case "$MODE" in
  stage) exec "$PY" benchmarks/gpu_wheels.py stage --stage "$STAGE_DIR" ;;
  run) ;;
  *) echo "usage: $0 stage|run" >&2; exit 2 ;;
esac

{
  echo "date: $(date -u +%FT%TZ)  host: $(uname -m), $(nproc) CPUs, $("$PY" --version 2>&1)"
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
    || echo "nvidia-smi: not found or failed"
} | tee "$OUT/gpu_host.txt"

if compgen -G ".gpu-wheels/part-*/MANIFEST.json" >/dev/null \
  || compgen -G "$STAGE_DIR/part-*/MANIFEST.json" >/dev/null; then
  "$PY" benchmarks/gpu_wheels.py unpack --stage "$STAGE_DIR" --target "$SITE"
  export PYTHONPATH="$SITE:$PWD"
else
  "$PY" -m venv .venv-gpu
  PY="$PWD/.venv-gpu/bin/python"
  if [ -f requirements/gpu.lock ]; then
    "$PY" -m pip install -q --require-hashes -r requirements/gpu.lock
  else
    # Until the install branch's requirements/gpu.lock lands: the dev lock, then onnxruntime-gpu
    # in place of the CPU onnxruntime (they share the module name; one must go).
    "$PY" -m pip install -q --require-hashes -r requirements/dev.lock
    "$PY" -m pip uninstall -q -y onnxruntime
    "$PY" -m pip install -q onnxruntime-gpu
  fi
  "$PY" -m pip install -q --no-deps --no-build-isolation -e .
  export PYTHONPATH="$PWD"
fi
export ELASTICFOG_CACHE_DIR="${ELASTICFOG_CACHE_DIR:-/tmp/ef-gpu/cache}"

# The CUDA and cuDNN libraries of the nvidia-* wheels (PyTorch's, on the GPU image) on the
# loader's path, whatever onnxruntime.preload_dlls finds by itself.
NV_LIBS="$("$PY" - <<'EOF'
import glob
import os
import site

found = set()
for base in site.getsitepackages():
    pattern = os.path.join(base, "nvidia", "**", "lib*.so*")
    found.update(os.path.dirname(p) for p in glob.glob(pattern, recursive=True))
print(":".join(sorted(found)))
EOF
)"
export LD_LIBRARY_PATH="${NV_LIBS}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
echo "nvidia libraries: ${NV_LIBS:-none}" | tee -a "$OUT/gpu_host.txt"

# What a session asking for each GPU provider really gets, as the daemons check it.
"$PY" - <<'EOF' 2>&1 | tee -a "$OUT/gpu_host.txt"
import onnxruntime as ort
from onnx import TensorProto, helper

from common.providers import check_session, ort_providers, parse_provider, prepare

x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])
y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])
graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y])
opset = [helper.make_opsetid("", 17)]
model = helper.make_model(graph, opset_imports=opset, ir_version=8).SerializeToString()
cpu = parse_provider("cpu")
prepare([parse_provider("cuda")])
print("onnxruntime:", ort.__version__, ort.__file__)
print("available:", ", ".join(ort.get_available_providers()))
for name in ("cuda", "tensorrt"):
    specs = [parse_provider(name), cpu]
    check = check_session(ort.InferenceSession(model, providers=ort_providers(specs)), specs)
    print(f"{name}: {check.message() if check.fell_back else 'gets ' + ', '.join(check.got)}")
EOF

# The GPU tests (skipped on a CPU build) and the CPU ones beside them; a failure is reported,
# and the benchmark still runs.
set +e
"$PY" -m pytest -q -p no:cacheprovider tests/unit/test_providers.py \
  tests/unit/test_split_runtime_gpu_serving.py 2>&1 | tee "$OUT/gpu_tests.log" | tail -5
# shellcheck disable=SC2086  # GPU_BENCH_ARGS is a list of options
timeout "$BENCH_TIMEOUT_S" "$PY" benchmarks/gpu_suffix.py --providers cpu,cuda,tensorrt \
  --serving-providers cpu,cuda,tensorrt --out "$OUT/gpu_suffix.json" ${GPU_BENCH_ARGS:-} \
  2> >(tee "$OUT/gpu_suffix.log" >&2) >/dev/null
code=$?
set -e
echo "gpu_suffix.py exited $code; results: $OUT/gpu_suffix.json"
exit "$code"
