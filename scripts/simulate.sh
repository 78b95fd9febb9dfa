#!/usr/bin/env bash
# Thin wrapper: simulate a tilt series (see `gaussian-atoms simulate --help`).
exec "$(dirname "$0")/../.venv/bin/gaussian-atoms" simulate "$@"
