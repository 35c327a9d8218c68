"""Driving policies that act on what an agent observes, with no simulator: the rule-based and
random drivers (:mod:`.drivers`), the safety shield that masks unsafe actions
(:mod:`.shield`), a trained policy exported to ONNX (:mod:`.onnx_policy`), and the frame stacks
they act on (:mod:`.frames`)."""
