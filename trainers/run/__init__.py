"""A training run: the loop (a lone run's, the members'), and its books: the environment's
parts, the replay on disk, the logs and metrics, the recording, the checkpoints and what an
exact resume puts back."""
