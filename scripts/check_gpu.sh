#!/usr/bin/env bash
# The GPU checks of docs/differentiable.md ("Variants"), for a machine with an NVIDIA GPU and
# sonarsim installed: the renderer's and the solvers' tests on cuda_ad_mono, and the
# histograms / gradients against arrays saved on the CPU by
#   python benchmarks/bench_backends.py --save REF.npz
# Usage: scripts/check_gpu.sh [REF.npz]   (run from the repository root)
set -uo pipefail
export SONARSIM_VARIANT=cuda_ad_mono PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
status=0
nvidia-smi -L || { echo "no NVIDIA GPU found"; exit 2; }
root=$(pwd)
# Run pytest from outside the checkout so that the installed sonarsim (with its plugins
# package) is imported rather than the source folders.
(cd /tmp && "$PY" -m pytest -q -p no:cacheprovider "$root/tests/test_differentiable.py" \
    "$root/tests/test_refine.py" "$root/tests/test_calibrate.py" "$root/tests/test_nbp.py" "$root/tests/test_gradient_descent.py" \
    "$root/tests/test_backprojection.py") || status=1
if [ $# -ge 1 ]; then
    "$PY" benchmarks/bench_backends.py --compare "$1" || status=1
else
    "$PY" benchmarks/bench_backends.py || status=1
fi
exit $status
