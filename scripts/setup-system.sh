#!/usr/bin/env bash
# Installs the Debian packages kinreg needs, only those that are missing (idempotent, fast when done).
# CHOLMOD headers for scikit-sparse, libusb for open3d, OpenBLAS so that CHOLMOD does not run on the
# reference BLAS (20,000-station factorisation: 130 s -> 9 s), a compiler and Python headers to build
# scikit-sparse, venv support for the virtual environment.
set -euo pipefail
need=()
have() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
for pkg in libsuitesparse-dev libusb-1.0-0 libopenblas0-pthread libgomp1; do
    have "$pkg" || need+=("$pkg")
done
command -v gcc >/dev/null 2>&1 || need+=(build-essential)
if ! python3 -c 'import sysconfig, os, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' 2>/dev/null; then
    need+=(python3-dev)
fi
python3 -c 'import ensurepip, venv' 2>/dev/null || need+=(python3-venv)
if [ ${#need[@]} -eq 0 ]; then
    exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
    echo "kinreg setup: missing Debian packages: ${need[*]}; run as root or install them with apt-get" >&2
    exit 1
fi
echo "kinreg setup: apt-get install ${need[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
