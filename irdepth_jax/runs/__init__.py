"""Run directories and checkpoints: what training writes and what evaluation, prediction and
export read. `checkpoint` (orbax: save, restore, the one lookup of a run's newest stage),
`variables` (a model's variables: initialised, loaded from a run or a released checkpoint, and
what the run was trained on), `legacy_names` (names older checkpoints were written under).
Training (`irdepth_jax.train`) and deployment (evaluate, predict, export) both use it; it imports
nothing of either."""
