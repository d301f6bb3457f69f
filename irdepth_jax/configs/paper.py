"""The `paper` preset: the paper's model sizes and training schedule (meant for a GPU)."""

from irdepth_jax.config_schema import Config


def get_config() -> Config:
    """The paper's MTSA-UNet widths (32, 64, 128, 256, bottleneck 512, 6 classes; 14.4 M
    parameters), Depth Anything V2 ViT-S (``vits``) at 252x322, 50 epochs per stage and the
    paper's batch sizes and rates, on 256x320 frames: the dataclass defaults. Meant for a GPU,
    with a released checkpoint (``depth.checkpoint=PATH``) and real data.

    Command: ``irdepth train stage1 --preset paper --data DIR --workdir runs/s1``, then
    ``irdepth train stage2 --preset paper --data DIR --workdir runs/s2 --stage1-checkpoint
    runs/s1``.

    Time: not timed end to end; its Stage I train step on a CPU (docs/benchmarks.md, ``python
    experiments/bench_unet.py --preset paper``) makes its 50-epoch stages impractical without
    an accelerator.
    """
    return Config(name="paper")
