"""Speed: for whoever asks how fast overtake simulates, serves, trains and records, and what
each part of a step costs. Every figure is a ratio to a peer measured in the same run, on the
same machine (highway-env and EnvPool on the same scene, in-process against remote, a bare
Zenoh round trip, another git revision's code paired with this one, PyTorch against ONNX
Runtime, recording off against on); bench/RESULTS.md keeps them with their commands.
"""
