# Sourced by scripts/demo and scripts/test: make a working environment on a fresh machine.
# - Debian packages listed in scripts/debian-packages.txt (only when running as root with apt-get);
# - a virtual environment in .venv with fbgcomp and every optional extra (the test extra brings the
#   linters), reinstalled when pyproject.toml or the version in src/fbgcomp/__init__.py changes.
# .ci/run sources it alone to make the environment before the linters run.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1 && [ -s scripts/debian-packages.txt ]; then
    missing=()
    while read -r pkg _; do
        case "$pkg" in ''|'#'*) continue ;; esac
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
    done < scripts/debian-packages.txt
    if [ "${#missing[@]}" -gt 0 ]; then
        echo "installing Debian packages: ${missing[*]}" >&2
        DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    fi
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    echo "creating virtual environment .venv" >&2
    "$PY" -m venv .venv
fi
stamp=".venv/.fbgcomp-installed"
# the version is read from src/fbgcomp/__init__.py at install time (pyproject: dynamic version)
want="$( (cat pyproject.toml; grep '^__version__' src/fbgcomp/__init__.py) | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "installing fbgcomp and its dependencies into .venv" >&2
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null
    .venv/bin/python -m pip install -q -e '.[all]'
    echo "$want" > "$stamp"
fi
