"""overtake.trainers: learners, networks, replay, checkpoints, training runs, experiments."""
