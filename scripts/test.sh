#!/usr/bin/env bash
# The project's test command: builds the binaries the multi-process tests launch, then runs
# every test tier (unit tests beside the code, each crate's tests/, and the top-level tests/
# that start real sim, agent and critic processes).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --workspace --bins
cargo test --workspace "$@"
