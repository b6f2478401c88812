# Sourced by benchmarks/device_check.sh and experiments/device_trainings.sh, from the repository root: the
# python ($PY), Ray and the rest from .bundle where that python lacks Ray (the accelerator machine), the cores
# ($CORES, counted before OMP_NUM_THREADS=1, which nproc obeys) and the environment every check runs in.
PY=${PYTHON:-python3}
if ! $PY -c "import ray" 2>/dev/null; then
  [ -f .bundle/site.tar.xz ] || { echo "$PY has no Ray and .bundle/site.tar.xz is missing: run bash benchmarks/device_bundle.sh here first, then carry .bundle" >&2; exit 2; }
  mkdir -p /tmp/site && xz -dc .bundle/site.tar.xz | tar -xf - -C /tmp/site || exit 1
  export PYTHONPATH=/tmp/site
fi
CORES=$(nproc)
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 RAY_AUTH_MODE=disabled
