#!/usr/bin/env bash
# Build the documentation site from docs/ into site/, warnings as errors and internal links
# checked (mkdocs.yml: strict, validation); --serve serves it at http://127.0.0.1:8000 and
# rebuilds on change instead. Installs the docs extra into .venv first.
# Usage: scripts/docs.sh [--serve]
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh docs
# Material for MkDocs prints a banner about its successor on every build; it says nothing
# about this site.
export NO_MKDOCS_2_WARNING=1
if [[ "${1:-}" == "--serve" ]]; then
  exec .venv/bin/mkdocs serve --strict --dev-addr 127.0.0.1:8000
fi
.venv/bin/mkdocs build --strict --clean
echo "the site is in site/ (open site/index.html, or: scripts/docs.sh --serve)"
