#!/usr/bin/env bash
# Thin wrapper: score predicted atoms against the truth (see `gaussian-atoms evaluate --help`).
exec "$(dirname "$0")/../.venv/bin/gaussian-atoms" evaluate "$@"
