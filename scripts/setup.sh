#!/usr/bin/env bash
# Set up everything deadreckon's tests need on a fresh Debian machine: system packages, a virtualenv, node packages.
# Idempotent; run from the project root. Uses only PyPI, Debian's packages and the npm registry.
set -euo pipefail
cd "$(dirname "$0")/.."

packages=$(grep -v '^\s*#' .ci/apt-packages.txt | tr '\n' ' ')
missing=""
for p in $packages; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[test]'

if [ -f tests/peers/package.json ]; then
  (cd tests/peers && npm install --no-audit --no-fund --silent)
fi
