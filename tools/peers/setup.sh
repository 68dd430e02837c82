#!/usr/bin/env bash
# Install the optional benchmark peers, each in its own virtual environment OUTSIDE the
# project's venv (so they can never break it): `make peers`.
#   motulator 0.18          -> $BIKE_PEERS_DIR/motulator  (Python 3.12: motulator needs it)
#   gym-electric-motor 3.0  -> $BIKE_PEERS_DIR/gem        (Python 3.11 or 3.12)
# Both also get numpy, numba and PyYAML: the peer scripts drive the peers' machine models
# with the project's own PI control law (bike_controller.spmsm_control), imported from src/.
# Idempotent: an environment that already imports its peer is left alone.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
peers_dir=${BIKE_PEERS_DIR:-$HOME/.cache/bike-peers}
mkdir -p "$peers_dir"

find_python() {  # find_python 3.12 -> path of a python3.12 (pyenv, then PATH)
    local v=$1 p
    for p in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/"$v".*/bin/python"$v" "$(command -v python"$v" || true)"; do
        if [ -n "$p" ] && [ -x "$p" ]; then echo "$p"; return 0; fi
    done
    return 1
}

make_env() {  # make_env NAME PYTHON_VERSIONS... -- PIP_SPECS...
    local name=$1; shift
    local versions=() specs=() py="" v
    while [ "$1" != "--" ]; do versions+=("$1"); shift; done; shift
    specs=("$@")
    local env="$peers_dir/$name"
    local module=${specs[0]%%[=<>]*}; module=${module//-/_}
    if [ -x "$env/bin/python" ] && "$env/bin/python" -c "import $module, numba, yaml" 2>/dev/null; then
        echo "peers: $name already installed in $env"
        return 0
    fi
    for v in "${versions[@]}"; do py=$(find_python "$v") && break; done
    if [ -z "$py" ]; then
        echo "peers: $name needs Python ${versions[*]} (none found; pyenv install ${versions[0]})" >&2
        return 1
    fi
    echo "peers: creating $env with $py"
    "$py" -m venv --clear "$env"
    "$env/bin/python" -m pip install -q --upgrade pip
    "$env/bin/python" -m pip install -q "${specs[@]}" numba pyyaml
    "$env/bin/python" -c "import $module; print('peers: $name', getattr($module, '__version__', ''), 'ready')"
}

status=0
make_env motulator 3.12 -- "motulator==0.18.*" || status=1
make_env gem 3.11 3.12 -- "gym-electric-motor==3.0.*" || status=1
echo "peers: environments under $peers_dir (BIKE_PEERS_DIR); run ./bike bench --only peers"
exit $status
