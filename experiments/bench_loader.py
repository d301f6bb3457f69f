"""Does the host side keep the device busy? Stage I-1 training images/s three ways, on one device:

  * step alone: the jitted train step on one batch held in device memory (the device's rate);
  * loader alone: the training `Loader` (PNG reading, augmentation, prefetch thread) with no
    step (the host's rate);
  * training: loader + step as `irdepth train` runs them (the prefetch thread reads the next
    batch while the step runs).

    python experiments/bench_loader.py --preset small --size 256x320 --steps 20

training / step alone near 1 means the loader never leaves the device idle; the host's rate
says how much headroom there is (on a 2-core CPU the loader's threads and XLA's share the
cores, so the overlap costs some step time there; a GPU has the cores to itself). Renders
--frames synthetic frames into a temporary folder dataset first. Medians over --repeats runs of
--steps batches each, the three interleaved.
"""

from __future__ import annotations

import argparse
import functools
import json
import tempfile
import time

import jax

from irdepth_experiments.bench_common import interleaved_medians, set_xla_threads, usable_cpus, wall_seconds, write_json
from irdepth_experiments.bench_unet import parse_size
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.source import BatchStream, DataSource, device_batch, make_loader, phase_frames
from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.state import TrainState, stage1_optimizer
from irdepth_jax.train.steps import make_train_step, stage1_loss_fn

PHASE = "stage1_i1"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="small", help="config preset (paper | small | tiny)")
    parser.add_argument("--size", type=parse_size, default=(256, 320), help="frame HxW")
    parser.add_argument("--frames", type=int, default=64, help="synthetic frames to render")
    parser.add_argument("--steps", type=int, default=20, help="batches per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=usable_cpus(), help="XLA intra-op threads")
    parser.add_argument("--json", metavar="FILE", help="also write the figures to FILE")
    args = parser.parse_args(argv)
    set_xla_threads(args.threads)
    h, w = args.size
    cfg = apply_overrides(get_config(args.preset), [f"data.height={h}", f"data.width={w}"])
    batch_size = cfg.stage1.batch_size

    with tempfile.TemporaryDirectory() as tmp:
        write_synthetic_dataset(tmp, n=args.frames, labeled=args.frames // 2, height=h, width=w,
                                progress=False)
        source = DataSource(tmp)
        dataset, indices = phase_frames(source, PHASE, cfg)
        stream = BatchStream(make_loader(dataset, indices, batch_size, cfg.seed, True, cfg))
        dp = DataParallel("single")
        step_fn = dp.train_step(make_train_step(stage1_loss_fn(cfg, PHASE), None,
                                                cfg.stage1.accum_steps), donate=False)
        variables = init_unet(cfg)
        tx, lr_fns = stage1_optimizer(cfg, PHASE)
        state = dp.replicate(TrainState.create(variables["params"], variables["batch_stats"], tx,
                                               jax.random.PRNGKey(0), lr_fns))
        held = dp.shard_batch(device_batch(next(stream), PHASE, cfg))
        jax.block_until_ready(step_fn(state, held, None))  # compile

        def step_alone():
            s = state
            for _ in range(args.steps):
                s, metrics = step_fn(s, held, None)
            jax.block_until_ready(metrics)

        def loader_alone():
            for _ in range(args.steps):
                device_batch(next(stream), PHASE, cfg)

        def training():
            s = state
            for _ in range(args.steps):
                s, metrics = step_fn(s, dp.shard_batch(device_batch(next(stream), PHASE, cfg)), None)
            jax.block_until_ready(metrics)

        start = time.perf_counter()
        timers = [functools.partial(wall_seconds, fn) for fn in (step_alone, loader_alone, training)]
        seconds = interleaved_medians(timers, args.repeats, warmup=1)
        wall = time.perf_counter() - start
    images = args.steps * batch_size
    result = {"preset": args.preset, "size": [h, w], "batch": batch_size, "steps": args.steps,
              "threads": args.threads, "device": str(jax.devices()[0]),
              "step_alone_img_per_s": images / seconds[0], "loader_alone_img_per_s": images / seconds[1],
              "training_img_per_s": images / seconds[2],
              "training_over_step_alone": seconds[0] / seconds[2], "wall_s": wall}
    print(json.dumps(result, indent=1))
    write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
