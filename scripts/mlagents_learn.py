"""mlagents-learn, with the ONNX export it ends with made by PyTorch's TorchScript-based
exporter (``dynamo=False``).

mlagents 1.1.0 calls ``torch.onnx.export`` without saying which exporter; PyTorch 2.9 and
later default to the torch.export-based one, which imports onnxscript, whose dependencies
(ml_dtypes >= 0.5, onnx-ir) need numpy >= 2, while mlagents 1.1.0 needs numpy < 1.24. The
older exporter needs neither and writes the same kind of model mlagents-learn wrote with the
PyTorch of its day. Run with .venv-mlagents-learn's Python, with mlagents-learn's arguments.
"""

from __future__ import annotations

import functools
import sys

import torch


def main() -> None:
    torch.onnx.export = functools.partial(torch.onnx.export, dynamo=False)
    from mlagents.trainers.learn import main as learn

    sys.argv[0] = "mlagents-learn"
    learn()


if __name__ == "__main__":
    main()
