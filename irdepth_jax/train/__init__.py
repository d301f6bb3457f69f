"""Staged training: states and optimizers, steps, data parallelism, checkpoints, the phase driver and the stages."""
