"""The `tiny` preset: seconds-sized models for the quickstart and the tests."""

from irdepth_jax.config_schema import (
    Config,
    DataConfig,
    DepthConfig,
    Stage1Config,
    Stage2Config,
    UNetConfig,
)


def get_config() -> Config:
    """A 9.4k-parameter MTSA-UNet (widths 4-4-4-4, bottleneck 8) and a 4-block, 32-wide ViT
    (encoder ``tiny``) on 96 rendered 64x80 frames: the whole pipeline in about a minute and a
    half on a CPU, for trying it out and for the test suite.

    Command: ``irdepth quickstart`` (its default preset; also
    ``irdepth train stage1 --preset tiny --data DIR --workdir runs/s1`` and ``stage2``, and
    ``python experiments/table1_preprocessing.py --quick``).

    Time: docs/getting-started.md gives the quickstart's measured wall time on a 2-core CPU.
    """
    # Tuned so that `irdepth quickstart` shows clear learning in a few minutes on 2 CPU cores:
    # per-image percentile input scaling, and AdamW instead of AdaDelta for Stage I (AdaDelta's
    # per-coordinate step starts near sqrt(eps) = 1e-3 and needs far more than ~200 updates).
    return Config(
        name="tiny",
        unet=UNetConfig(widths=(4, 4, 4, 4), bottleneck=8, raw_scale="percentile"),
        depth=DepthConfig(encoder="tiny", input_height=56, input_width=70),
        data=DataConfig(height=64, width=80, num_frames=96, num_labeled=48),
        stage1=Stage1Config(batch_size=4, epochs_i1=10, epochs_i2=8, accum_steps=2,
                            optimizer="adamw", learning_rate=3e-3, i2_learning_rate=5e-4),
        stage2=Stage2Config(batch_size=4, epochs=10, learning_rate=2e-4),
        log_every=5,
        eval_every=50,
        checkpoint_every=50,
    )
