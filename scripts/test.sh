#!/usr/bin/env bash
# The project's test command: builds the binaries the multi-process tests launch, then runs
# every test tier (unit tests beside the code, each crate's tests/, and the top-level tests/
# that start real sim, agent and critic processes), then the Python client's tests
# (python/tests: layout conformance and real runs with a robot played from Python).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --workspace --bins
cargo test --workspace "$@"
# What .ci/run installs for the Python tests; a test file whose extra is missing is skipped.
python_extras='python3 -m pip install "./python[pettingzoo,test]" "eclipse-zenoh>=1.0,<2" rosbags mcap mcap-ros2-support'
if python3 -c 'import iceoryx2, pytest' >/dev/null 2>&1; then
  echo "test.sh: python tests (python/tests, binaries from target/debug)"
  if ! python3 -c 'import pettingzoo, gymnasium, numpy, supersuit, zenoh, rosbags, mcap, mcap_ros2, matplotlib' >/dev/null 2>&1; then
    echo "test.sh: some python test files will be skipped (their extras are missing): $python_extras"
  fi
  # The package under test is this checkout's python/ (installed or not).
  # The binaries cargo just built (CI may point CARGO_TARGET_DIR outside the clone).
  bin_dir=$(cd "${CARGO_TARGET_DIR:-target}/debug" && pwd)
  (cd python && FORMATION_BIN_DIR="${FORMATION_BIN_DIR:-$bin_dir}" PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" \
    python3 -m pytest -q tests)
else
  echo "test.sh: skipping the python tests: python3 cannot import iceoryx2 and pytest ($python_extras)"
fi
