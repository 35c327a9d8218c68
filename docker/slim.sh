#!/bin/sh
# What the services never run, removed from the venv in the same RUN as its install (a later
# layer could hide files, not shrink the image; bench/RESULTS.md, "The images", has the sizes).
#   slim torch      after PyTorch's install (the trainer image's first install step)
#   slim server     at the end of the server image: the simulator, router, spectators, viewer
#   slim trainer    at the end of the trainer image: overtake-train / overtake-eval, which
#                   record to a file or stream to a viewer and never run one
set -eu
site=$(python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
# Every package's own test suite (numpy, pyarrow, sympy, networkx, ...): never imported.
find "$site" -depth -type d -name tests -exec rm -rf {} +
case "${1:-}" in
torch)
    # PyTorch's C++ test binaries and test data, its protobuf compiler and its C++ headers
    # (for torch.compile's C++ code generation and C++ extensions, which overtake does not
    # use); torch_shm_manager stays (tensors shared between processes).
    find "$site/torch/bin" -mindepth 1 ! -name torch_shm_manager -exec rm -rf {} +
    rm -rf "$site/torch/test" "$site/torch/include"
    exit 0
    ;;
trainer)
    # The Rerun viewer's binary: a trainer records to a file or streams to the viewer service
    # (overtake-train --sink web says so where it is missing).
    rm -f "$site/rerun_cli/rerun"
    ;;
server) ;;
*)
    echo "slim: expected torch, server or trainer, got '${1:-}'" >&2
    exit 2
    ;;
esac
# C headers and sources, for building extensions against pyarrow.
rm -rf "$site/pyarrow/include" "$site/pyarrow/src"
# pip itself stays: it came with the venv in an earlier layer, where removing it saves nothing.
