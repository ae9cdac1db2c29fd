#!/usr/bin/env bash
# Installs what the tests need (scripts/install.sh), then runs the default (fast) test suite.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -m slow` for the long tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The tests cover `simgen make --ray`, so its optional extra too (once; ray pulls in no torch).
.venv/bin/python -c "import ray" 2>/dev/null || .venv/bin/python -m pip install -q -e ".[dev,ray]"
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
exec .venv/bin/python -m pytest -q "$@"
