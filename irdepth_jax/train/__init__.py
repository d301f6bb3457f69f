"""Staged training: states and optimizers, steps, data parallelism, checkpoints, loops."""
