"""What every test needs, and nothing heavier: fixtures that start servers (Zenoh) live in
the conftest.py of the folders whose tests use them, and scripted scenes (the simulator) in
tests/support/scenes.py, imported by the tests that script one, so that a protocol test loads
neither."""

from __future__ import annotations

import os

# ML-Agents' protobuf code (mlagents-envs 1.1.0, tests/client/test_mlagents.py) predates
# protobuf 4, which ONNX needs: protobuf's pure-Python implementation reads both. It is picked
# when protobuf is first imported, so before any test module imports it (every worker collects
# every file, the ONNX tests' with the ML-Agents tests').
os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")
