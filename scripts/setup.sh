#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install drago into it.
# Idempotent: a second call with unchanged requirements returns in about a second.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
    echo "setup: drago needs Python >= 3.10 (found: $("$PYTHON" --version 2>&1)); set PYTHON=/path/to/python3.x" >&2
    exit 2
fi
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi

# constraints.txt pins torch to the CPU build for this set-up path (the package itself accepts any
# torch >= 2.1, so GPU users can install their own build first) and dm-control / mujoco to a pair that
# works. The dmc extra brings DeepMind Control (cheetah, walker), which the test suite covers; the docs
# extra brings MkDocs, whose site build the test suite checks too; the wandb extra, Weights & Biases, whose
# offline mode the tests use.
stamp=.venv/.drago-install-stamp
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[dmc,test,docs,slurm,wandb]'
    echo "$want" > "$stamp"
fi

# Debian packages some features need: install them where they are missing and apt-get can (root or
# password-less sudo); elsewhere only that feature is unavailable, never training, and its test is
# skipped with the reason. The cached package lists are tried first: an apt-get update costs time.
apt_install() {
    command -v apt-get >/dev/null 2>&1 || return 1
    local sudo=()
    if [ "$(id -u)" != 0 ]; then
        sudo -n true 2>/dev/null || return 1
        sudo=(sudo -n)
    fi
    local apt=("${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get -y -qq --no-install-recommends)
    echo "setup: installing $* (Debian packages)"
    "${apt[@]}" install "$@" >/dev/null 2>&1 && return 0
    "${sudo[@]}" apt-get update -qq >/dev/null 2>&1 && "${apt[@]}" install "$@" >/dev/null 2>&1
}

# Headless rendering of cheetah / walker episodes (GIF) uses EGL with Mesa's software driver (MUJOCO_GL=egl).
have_egl() {
    local libs
    libs=$({ command -v ldconfig >/dev/null && ldconfig -p || /sbin/ldconfig -p; } 2>/dev/null || true)
    [[ "$libs" == *libEGL_mesa.so.0* ]]
}
if [ "$(uname -s)" = Linux ] && ! have_egl; then
    apt_install libegl1 libegl-mesa0 libgl1-mesa-dri || true
    have_egl || echo "setup: could not install EGL (needs apt-get and root or password-less sudo); videos of cheetah / walker cannot be rendered headless"
fi

# The report's browser test opens a generated page in a real headless Chromium, from Debian's package.
if ! command -v chromium >/dev/null 2>&1; then
    apt_install chromium || true
    command -v chromium >/dev/null 2>&1 || echo "setup: could not install chromium (needs apt-get and root or password-less sudo); the report's browser test will be skipped"
fi

# --- SLURM test cluster (tests/slurm_cluster.py) ---------------------------------------------------------------------
# The SLURM tests start a real one-node cluster on 127.0.0.1 from Debian's slurm-wlm (slurmctld, slurmd and the client
# commands sbatch, squeue, scancel, sinfo) and munge (munged). Nothing is configured or started here: the test fixture
# runs private daemons with its own key, socket, slurm.conf and ports. (Where systemd runs, the packages enable their own
# munge / slurmctld / slurmd services; without an /etc/slurm/slurm.conf the SLURM ones do not start.)
have_slurm() {
    local p
    for p in slurmctld slurmd sbatch squeue scancel sinfo munged; do
        command -v "$p" >/dev/null 2>&1 || [ -x "/usr/sbin/$p" ] || return 1
    done
}
if [ "$(uname -s)" = Linux ] && ! have_slurm; then
    apt_install slurm-wlm munge || true
    have_slurm || echo "setup: could not install slurm-wlm and munge (needs apt-get and root or password-less sudo); the SLURM cluster tests will be skipped"
fi
