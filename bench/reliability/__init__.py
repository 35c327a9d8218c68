"""Reliability: for whoever runs overtake for hours, on several hosts or in containers, and
asks what survives. Trainers sharing one server fairly, load until the step's p99 doubles,
security's cost per step, an hour's soak of learners and recordings (memory, rates, queues),
processes killed, frozen or cut off the network, and the compose stack end to end on a Docker
engine; bench/RELIABILITY.md keeps the figures with their commands.
"""
