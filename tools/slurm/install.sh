#!/usr/bin/env bash
# Debian's SLURM and munge for tests/test_slurm.py, when they are missing and apt-get can install
# them (as root). Never fails: where SLURM cannot be installed, it says why and the test skips.
set -uo pipefail
if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null; then
    exit 0
fi
if [[ $(id -u) -ne 0 ]] || ! command -v apt-get >/dev/null; then
    echo "SLURM is not installed and cannot be here (needs root and apt-get): tests/test_slurm.py skips"
    exit 0
fi
echo "installing SLURM and munge (apt-get install slurm-wlm munge) for tests/test_slurm.py"
if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null; }; then
    echo "apt-get could not install SLURM: tests/test_slurm.py skips"
fi
exit 0
