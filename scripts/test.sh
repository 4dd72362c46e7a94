#!/usr/bin/env bash
# Set up (idempotent) and run the whole test suite, after the lint, format and layering checks.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
python3 -m ruff check src tests benchmarks tools docs/examples
python3 -m ruff format --check src tests benchmarks tools docs/examples
PYTHONPATH=src python3 -c "from importlinter.cli import lint_imports_command as c; c()"  # `lint-imports`: the package layers and "typer only in t2bs.cli" (pyproject.toml [tool.importlinter])
python3 -m pytest -q "$@"
