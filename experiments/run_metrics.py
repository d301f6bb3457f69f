"""The metrics of a cached run on the evaluation frames (`irdepth_experiments.cache.Context.result`):
aggregated, and per frame for `irdepth_experiments.claims`."""

from __future__ import annotations


def stage1_metrics(cfg, workdir: str, dataset, indices, seg_frames) -> tuple[dict, dict]:
    """Stage I metrics of the run in `workdir`: reconstruction on the depth frames `indices` of
    `dataset`, mIoU (tables 3 and 6) on the segmentation frames `seg_frames` (the paper's
    independent 600/100/100 split). Returns ({'stage1': metrics}, per-frame arrays)."""
    from irdepth_jax.evaluators import evaluate_stage1
    from irdepth_jax.runs.variables import load_stage1
    from irdepth_jax.train.parallel import DataParallel

    unet, _ = load_stage1(workdir, cfg)
    metrics, frames = evaluate_stage1(cfg, unet, dataset, indices, DataParallel("single"),
                                      seg_frames=seg_frames, per_frame=True)
    return {"stage1": metrics}, frames


def stage2_metrics(cfg, workdir: str, dataset, indices, align: str | None,
                   train_max_depth: float) -> tuple[dict, dict]:
    """Depth metrics of the run in `workdir` on frames `indices` of `dataset`, under the
    protocol's alignment `align` ('stage2') and median-scaled per image ('stage2_median'), from
    one prediction per frame; 'stage2' also holds the sky metrics (`metrics.SKY_METRICS`, on the
    labelled frames, against the run's sky reference depth from the training data's largest
    depth `train_max_depth`). Returns (metrics, per-frame arrays)."""
    from irdepth_jax.evaluators import accumulate_depth
    from irdepth_jax.metrics import DepthMetricAccumulator, SkyMetricAccumulator
    from irdepth_jax.runs.variables import load_model
    from irdepth_jax.train.parallel import DataParallel
    from irdepth_jax.train.stages import sky_reference_depth

    _, _, model = load_model(workdir, [])
    accs = {key: DepthMetricAccumulator(mode, cfg.data.min_depth, cfg.data.max_depth, keep_per_image=True)
            for key, mode in (("stage2", align), ("stage2_median", "median"))}
    sky = SkyMetricAccumulator(sky_reference_depth(cfg, train_max_depth),
                               min_depth=cfg.data.min_depth, max_depth=cfg.data.max_depth)
    accumulate_depth(cfg, model["unet"], model["depth"], dataset, indices,
                     DataParallel("single"), list(accs.values()), [sky])
    frames = {f"{key}/{k}": v for key, acc in accs.items() for k, v in acc.per_image().items()}
    frames.update({f"stage2/{k}": v for k, v in sky.per_image().items()})
    metrics = {key: acc.result() for key, acc in accs.items()}
    for group, values in sky.result().items():
        metrics["stage2"].setdefault(group, {}).update(values)
    return metrics, frames
