"""The whole training story, top to bottom, as one library function (flax `examples/imagenet`
style): `train_and_evaluate(cfg, workdir)` renders a synthetic dataset (or takes yours), trains
Stage I (I-1 reconstruction pre-training, I-2 soft multi-task) and Stage II (Depth Anything V2 on
the HSV pseudo-RGB, SiLog + sky loss), and evaluates both on the test split against the same
models untrained. `irdepth quickstart`, the learning tests and `notebooks/quickstart.ipynb` call
it; from a notebook:

    from irdepth_jax.config import get_config
    from irdepth_jax.workflow import train_and_evaluate
    result = train_and_evaluate(get_config("tiny"), "runs/quick")
    print(result["tables"])
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

from irdepth_jax.config import Config
from irdepth_jax.data.source import DataSource, resolve_raw_bits
from irdepth_jax.evaluate import evaluate_run
from irdepth_jax.evaluators import evaluate_stage1, evaluate_stage2
from irdepth_jax.runs.variables import init_depth, init_unet
from irdepth_jax.train.phase import RunOptions, make_parallel
from irdepth_jax.train.stages import train_stage1, train_stage2


def synthetic_data(cfg: Config, path: str, progress: bool = True) -> str:
    """Renders `cfg.data.num_frames` synthetic frames (`num_labeled` labelled) of
    `cfg.data.height` x `width` into a folder-format dataset at `path`; returns `path`."""
    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    d = cfg.data
    write_synthetic_dataset(path, d.num_frames, d.num_labeled, d.height, d.width, seed=cfg.seed,
                            progress=progress, scenes=d.scenes)
    return path


def train_and_evaluate(cfg: Config, workdir: str, data: str | None = None,
                       devices: int | None = None, progress: bool = True,
                       log: Callable[[str], None] = print) -> dict:
    """Stage I, Stage II and their test-split evaluation into `workdir`.

    Args:
      cfg: the run's config (e.g. `config.get_config('tiny')`).
      workdir: a new directory: ``data/`` (when `data` is None), ``stage1/``, ``stage2/``
        (runs, see `train.runlog`) and ``stage2/eval_test.md`` / ``.json``.
      data: a dataset directory (folder format or MS2); None renders a synthetic one.
      devices: number of devices (None: all).
      progress: progress bars.
      log: where the step headings go (``[1/4] ...``).
    Returns:
      ``{'data': dataset path, 'config': the config trained (raw bits resolved), 'before':
      {'stage1', 'stage2'}, 'after': {'stage1', 'stage2'}}`` (each the ``all`` row of the test
      split's metrics: psnr / ssim / entropy / miou; d1 / abs_rel / rmse ...), ``'tables'``
      (Markdown of `evaluate.evaluate_run`), ``'result'`` (its whole result) and ``'seconds'``.
    """
    start = time.perf_counter()
    d = cfg.data
    if data is None:
        data = os.path.join(workdir, "data")
        log(f"[1/4] synthetic dataset: {d.num_frames} frames ({d.num_labeled} labelled), "
            f"{d.height}x{d.width} -> {data}")
        synthetic_data(cfg, data, progress)
    else:
        log(f"[1/4] dataset: {data}")
    source = DataSource(data, raw_bits=cfg.data.raw_bits)
    cfg = resolve_raw_bits(cfg, source)  # the evaluations below use it too
    common = dict(devices=devices, progress=progress)
    log("[2/4] Stage I: I-1 reconstruction pre-training, I-2 soft multi-task")
    stage1_dir, stage2_dir = os.path.join(workdir, "stage1"), os.path.join(workdir, "stage2")
    s1 = train_stage1(cfg, source, RunOptions(stage1_dir, **common))
    log("[3/4] Stage II: Depth Anything V2 on the HSV pseudo-RGB")
    train_stage2(cfg, source, RunOptions(stage2_dir, **common, stage1_checkpoint=stage1_dir))
    log("[4/4] evaluation on the test split")
    dp = make_parallel(RunOptions(workdir, **common), cfg.stage2.batch_size)
    dataset, test = source.frames("test")
    before = {"stage1": evaluate_stage1(cfg, init_unet(cfg), dataset, test, dp,
                                        seg_frames=source.seg_frames("test"))["all"],
              "stage2": evaluate_stage2(cfg, s1["unet"], init_depth(cfg)[0], dataset, test,
                                        dp)["all"]}
    result = evaluate_run(stage2_dir, data, "test", dp=dp)
    after = {"stage1": result["stage1"]["all"], "stage2": result["stage2"]["all"]}
    return {"data": data, "config": cfg, "before": before, "after": after,
            "tables": result["markdown"], "result": result,
            "seconds": time.perf_counter() - start}


def improvement_lines(result: dict) -> list[str]:
    """The untrained -> trained change of `train_and_evaluate`'s result, as printed lines."""
    b1, b2 = result["before"]["stage1"], result["before"]["stage2"]
    a1, a2 = result["after"]["stage1"], result["after"]["stage2"]
    return ["untrained -> trained (test split):",
            f"  Stage I  PSNR {b1['psnr']:.2f} -> {a1['psnr']:.2f} dB, "
            f"SSIM {b1['ssim']:.3f} -> {a1['ssim']:.3f}, mIoU {b1['miou']:.3f} -> {a1['miou']:.3f}",
            f"  Stage II d1 {b2['d1']:.3f} -> {a2['d1']:.3f}, "
            f"AbsRel {b2['abs_rel']:.3f} -> {a2['abs_rel']:.3f}"]
