#!/usr/bin/env bash
# The solver benchmarks on a GPU machine (the device tool's NVIDIA H200): one prepared run.
#
#   bash benchmarks/gpu.sh            # results under $OUT (the device tool's output folder),
#                                     # else benchmarks/results/gpu/
#
# The machine has JAX with CUDA, equinox, lineax, optimistix, diffrax, optax, SciPy and
# matplotlib; PyAMG, cholespy, meshio and scikit-fem travel as wheels in .whl/ (see
# benchmarks/README.md). If difftissue does not run on the machine's versions of the JAX
# libraries, the pinned ones in .whl/ are used instead. Each step has its own time limit and
# writes its results as it goes, so a step cut short still leaves the earlier ones.
set -u
OUT=${OUT:-benchmarks/results/gpu}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
PY=python3
if [ -d .whl ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
    .whl/pyamg-*.whl .whl/cholespy-*.whl .whl/meshio-*.whl .whl/scikit_fem-*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
fi
versions() {
  $PY -c "import importlib.metadata as m, jax; print(jax.devices()); print(*(f'{p} {m.version(p)}' for p in ('jax', 'jaxlib', 'equinox', 'lineax', 'optimistix', 'diffrax', 'optax', 'numpy', 'scipy', 'pyamg')), sep='; ')"
}
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; lscpu | grep -E '^(Model name|CPU\(s\))'; versions; } 2>&1 | tee "$OUT/env.txt"
if ! timeout 90 $PY benchmarks/static.py --sizes 4 --models fem_linear --solvers multigrid-direct --out /tmp/smoke; then
  echo "smoke run failed on the machine's JAX libraries: using the pinned wheels" | tee -a "$OUT/env.txt"
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/pinned \
    .whl/equinox-*.whl .whl/lineax-*.whl .whl/optimistix-*.whl .whl/diffrax-*.whl .whl/optax-*.whl || exit 1
  export PYTHONPATH=/tmp/pinned:$PYTHONPATH
  versions | tee -a "$OUT/env.txt"
  timeout 90 $PY benchmarks/static.py --sizes 4 --models fem_linear --solvers multigrid-direct --out /tmp/smoke || exit 1
fi
# 1. 106k unknowns, both models: the GPU solve beside PyAMG's own (host) solver
timeout ${T1:-180} $PY benchmarks/static.py --sizes 20 --models fem_linear,springs_volume --solvers multigrid-direct,pyamg \
  --timeout 170 --out "$OUT/static-gpu"
pkill -f "static.py --child"  # a child left by a step cut short
# 2. 418k and 1M unknowns, fem_linear
timeout ${T2:-170} $PY benchmarks/static.py --sizes 32,43 --models fem_linear --solvers multigrid-direct --timeout 165 --out "$OUT/static-gpu"
pkill -f "static.py --child"
# 3. 16 batched 3k-tet indentation fits against the serial loop of fit
timeout ${T3:-120} $PY benchmarks/batch.py --skip serial-recompile,sharded,scaling --json "$OUT/batch-gpu.json" | tee "$OUT/batch-gpu.md"
ls -la "$OUT"
