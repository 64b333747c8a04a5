#!/usr/bin/env bash
# The GPU check as one command, on a GPU machine with no package index whose Python has its own CUDA PyTorch:
# installs the wheels carried in .whl/ (docs/guide/developer.md, "A GPU check") into .gpu-site/ and runs
# benchmarks/device_check.py, which prints one table (CUDA graph skips, compiled against eager on CUDA, learn() rates).
# Arguments go to device_check.py, e.g. `bash benchmarks/device_check.sh --sections speed`.
set -euo pipefail
cd "$(dirname "$0")/.."
if compgen -G ".whl/*.whl" > /dev/null; then
    # --upgrade: on a machine still warm from an earlier call, replace the copy there instead of warning per package
    python3 -m pip install -q --upgrade --no-index --no-deps --no-compile --target .gpu-site .whl/*.whl
fi
export PYTHONPATH="$PWD/.gpu-site:$PWD" PYTHONUNBUFFERED=1 MUJOCO_GL=egl XLA_PYTHON_CLIENT_PREALLOCATE=false
python3 -c "import torch, sb3_sera; print('torch', torch.__version__, 'on', torch.cuda.get_device_name())"
exec python3 benchmarks/device_check.py "$@"
