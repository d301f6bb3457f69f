"""Model variables in one place: fresh ones (`init_unet`, `random_depth`, `init_depth` from
released Depth Anything V2 weights) and stored ones (`load_stage1` for Stage II, `load_model`
for eval / predict / export; `train.state.save_model` writes a model those read).
"""

from __future__ import annotations

import functools
from collections.abc import Collection, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from irdepth_jax.config import STAGE1_IMAGES, STAGE1_MODEL_KEYS, Config, from_dict, get_key, to_dict, with_keys
from irdepth_jax.errors import RunError, one_line
from irdepth_jax.models.pipeline import depth_model_config
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.program_cache import cached_shapes
from irdepth_jax.runs.checkpoint import FINALIZED, CheckpointError, find_checkpoint, read_meta, restore_items

STAGE1_STAGES = ("stage1_i2", "stage1_i1")
"""Checkpoints a Stage II run starts from: I-2, or I-1 when there is no I-2."""

def init_key(seed: int) -> jax.Array:
    """Parameter-initialisation key. The 'rbg' generator: XLA compiles a model's init (one
    random draw per parameter) several times faster than with the default threefry."""
    return jax.random.key(seed, impl="rbg")


@functools.partial(jax.jit, static_argnums=0)
def _init_unet(unet_cfg, key):
    return MTSAUNet(unet_cfg).init(key, jnp.zeros((1, 32, 32), jnp.float32), train=False)


def init_unet(cfg: Config) -> dict:
    """Fresh MTSA-UNet variables {'params', 'batch_stats'} (seed cfg.seed; any frame size)."""
    variables = _init_unet(cfg.unet, init_key(cfg.seed))
    return {"params": variables["params"], "batch_stats": variables["batch_stats"]}


@functools.partial(jax.jit, static_argnums=(0, 1))
def _init_depth(da_cfg, size, key):
    from irdepth_jax.models.depth_anything import DepthAnythingV2
    return DepthAnythingV2(da_cfg).init(key, jnp.zeros(size, jnp.float32))["params"]


def random_depth(cfg: Config) -> dict:
    """Random Depth Anything V2 params of `cfg.depth` (seed cfg.seed + 1): Stage II's start
    without a checkpoint, and the template a Stage II checkpoint is restored into."""
    return _init_depth(depth_model_config(cfg),
                       (1, cfg.depth.input_height, cfg.depth.input_width, 3),
                       init_key(cfg.seed + 1))


def unet_shapes(cfg: Config) -> dict:
    """`init_unet`'s tree as ShapeDtypeStructs (traced, not compiled or run; kept in the
    program cache, `program_cache.cached_shapes`): the template a Stage I model is restored
    into."""
    return cached_shapes("unet_shapes", to_dict(cfg), lambda: jax.eval_shape(lambda: init_unet(cfg)))


def depth_shapes(cfg: Config) -> dict:
    """`random_depth`'s tree as ShapeDtypeStructs (as `unet_shapes`): the template Depth
    Anything V2 params are restored into."""
    return cached_shapes("depth_shapes", to_dict(cfg),
                         lambda: jax.eval_shape(lambda: random_depth(cfg)))


def init_depth(cfg: Config) -> tuple[dict, dict[str, str]]:
    """Stage II's starting Depth Anything V2 params and a description of where they came from.

    Without `depth.checkpoint`: `random_depth`. With it (a released .pth / .safetensors file, or
    a run directory of ours whose last stage trained Depth Anything V2: `irdepth train depth`
    or a Stage II): the backbone from it, and its head by `depth.load_head`: 'auto' when the
    file's head kind (`depth.checkpoint_kind`, see `weights.load_depth_anything`; a run's
    `depth.metric`) is the one `depth.metric` trains, else a random head (how the official
    metric fine-tuning starts from a relative checkpoint); True the file's head, refused when
    the kinds differ; False a random head.

    Returns (params, {'backbone': str, 'head': str}, plus 'max_depth': str when a loaded metric
    head was trained for another range than `depth.max_depth`), for `RunLog.info`. Raises
    RunError (one line naming the key or the file) for a bad setting, a missing, unreadable or
    ambiguous file, or load_head=true with the other head kind.
    """
    d = cfg.depth
    if not d.checkpoint:
        return random_depth(cfg), {"backbone": "random init (no depth.checkpoint)",
                                   "head": "random init (no depth.checkpoint)"}
    file_cfg, loaded = _depth_of_run(d.checkpoint, cfg) if _is_run(d.checkpoint) else _depth_of_file(d)
    file_kind, kind = ("metric" if m else "relative" for m in (file_cfg.metric, d.metric))
    params = {**random_depth(cfg), "pretrained": loaded["pretrained"]}
    described = {"backbone": f"loaded from {d.checkpoint} (encoder {d.encoder})"}
    if d.load_head is False:
        described["head"] = "random init: depth.load_head=false"
    elif file_kind != kind and d.load_head is True:
        raise RunError(f"depth.load_head=true: {d.checkpoint} holds a {file_kind} head, "
                       f"depth.metric={str(d.metric).lower()} trains a {kind} one: set "
                       "depth.load_head=auto (backbone only), the other depth.metric, or "
                       "depth.checkpoint_kind if the file's kind is misread")
    elif file_kind != kind:
        described["head"] = (f"random init: {d.checkpoint} holds a {file_kind} head, "
                             f"depth.metric={str(d.metric).lower()} trains a {kind} one "
                             "(backbone only, as the official metric fine-tuning starts)")
    else:
        params["depth_head"] = loaded["depth_head"]
        depth_range = f", max_depth {file_cfg.max_depth:g} m" if file_cfg.metric else ""
        described["head"] = f"loaded from {d.checkpoint} ({file_kind}{depth_range})"
        if file_cfg.metric and file_cfg.max_depth != d.max_depth:
            described["max_depth"] = (
                f"warning: the head was trained for max_depth {file_cfg.max_depth:g} m; "
                f"depth.max_depth={d.max_depth:g} scales its output by "
                f"{d.max_depth / file_cfg.max_depth:.3g}")
    return params, described


def _depth_of_file(d) -> tuple[Any, dict]:
    """(DepthAnythingConfig, params) of a released checkpoint file (`weights`)."""
    from irdepth_jax.weights import load_depth_anything
    try:
        return load_depth_anything(d.checkpoint, encoder=d.encoder, kind=d.checkpoint_kind,
                                   max_depth=d.max_depth)
    except (OSError, ValueError) as err:
        raise RunError(f"depth.checkpoint: {one_line(err)}") from None


def _is_run(path: str) -> bool:
    """Whether `path` is one of our run directories or checkpoint directories."""
    try:
        find_checkpoint(path)
        return True
    except CheckpointError:
        return False


def _depth_of_run(path: str, cfg: Config) -> tuple[Any, dict]:
    """(DepthAnythingConfig, params) of the Depth Anything V2 a run of ours trained, refused
    (RunError naming the keys) when its architecture is not `cfg`'s."""
    run_cfg, stage, model = load_model(path)
    if model["depth"] is None:
        raise RunError(f"depth.checkpoint {path}: a {stage} run, which has no depth network "
                       "(irdepth train depth or stage2 trains one)")
    if run_cfg.depth.encoder != cfg.depth.encoder:
        raise RunError(f"depth.checkpoint {path}: trained with depth.encoder="
                       f"{run_cfg.depth.encoder}, this run has depth.encoder={cfg.depth.encoder}")
    template = depth_shapes(cfg)
    shapes = [jax.tree_util.tree_structure(template), jax.tree_util.tree_structure(model["depth"])]
    if shapes[0] != shapes[1] or any(
            a.shape != b.shape for a, b in zip(jax.tree.leaves(template), jax.tree.leaves(model["depth"]))):
        raise RunError(f"depth.checkpoint {path}: its Depth Anything V2 parameters do not fit this "
                       "run's depth settings (depth.* must match the run's config.json)")
    return depth_model_config(run_cfg), model["depth"]


def take_stage1_settings(path: str, cfg: Config, explicit: Collection[str] = ()
                         ) -> tuple[Config, dict[str, tuple[Any, Any]]]:
    """`cfg` with every setting that defines the Stage I model (`STAGE1_MODEL_KEYS`: the UNet's
    sizes and switches, its raw normalisation, the bit depth) taken from the Stage I run at
    `path`, the config that Stage II then stores, so that eval and predict rebuild the model it
    was trained with.

    Args:
      path: the Stage I run (workdir or checkpoint directory), as for `load_stage1`.
      cfg: the Stage II run's config.
      explicit: dotted keys the user set (``key=value``); one of them set to another value
        than Stage I's is refused (data.raw_bits=auto is not: it resolves to Stage I's).
    Returns:
      (config, {key: (value in `cfg`, Stage I's value)} for each setting that changed).
    Raises:
      RunError naming the key (or the missing checkpoint).
    """
    try:
        directory, _ = find_checkpoint(path, STAGE1_STAGES)
        stored = from_dict(read_meta(directory)["config"])
    except CheckpointError as err:
        raise RunError(f"`stage1_checkpoint`: {err}") from None
    changed = {}
    for key in STAGE1_MODEL_KEYS:
        mine, theirs = get_key(cfg, key), get_key(stored, key)
        if mine == theirs or (key == "data.raw_bits" and mine == "auto"):
            continue
        if key in explicit:
            trained = (f"Stage I was trained on {theirs}-bit raw counts" if key == "data.raw_bits"
                       else f"the Stage I model has {key}={_word(theirs)}")
            raise RunError(f"`stage1_checkpoint` {path}: {trained}, this run sets "
                           f"{key}={_word(mine)}; Stage II takes {key} from Stage I: leave it "
                           "out, or retrain Stage I with it")
        changed[key] = (mine, theirs)
    return with_keys(cfg, {key: new for key, (_, new) in changed.items()}), changed


def _word(value: Any) -> str:
    """A config value as it is written in a ``key=value`` override."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def load_stage1(path: str, cfg: Config) -> tuple[dict, dict]:
    """Stage I variables from a Stage I run and what its segmentation branch was trained on:
    ``{'labeled_frames': N, ...}`` (0 after I-1 only or I-2 without labels; None for an I-2
    checkpoint written before this was recorded). One-line RunError if missing or mismatched,
    or trained on raw counts of another bit depth than `cfg.data.raw_bits`."""
    try:
        directory, stage = find_checkpoint(path, STAGE1_STAGES)
        items, meta = restore_items(directory, stage, {"model": unet_shapes(cfg)})
        unet = dict(items["model"])
    except CheckpointError as err:
        raise RunError(f"`stage1_checkpoint`: {err}") from None
    # checkpoints written before data.raw_bits existed were trained on 14-bit counts
    trained_bits = meta.get("config", {}).get("data", {}).get("raw_bits", 14)
    if trained_bits != cfg.data.raw_bits:
        raise RunError(f"`stage1_checkpoint` {path}: Stage I was trained on {trained_bits}-bit "
                       f"raw counts, this run has data.raw_bits={cfg.data.raw_bits}; use "
                       f"data.raw_bits={trained_bits} (the same data) or retrain Stage I")
    if meta.get("stage") == "stage1_i1":
        return unet, {"labeled_frames": 0, "why": "Stage I-1 only (no I-2 checkpoint)"}
    return unet, meta.get("segmentation") or {"labeled_frames": None,
                                              "why": "not recorded (older checkpoint)"}


def read_trained_on(path: str, stages: Sequence[str] = ("stage2", "stage1_i2", "stage1_i1")
                    ) -> dict | None:
    """What the latest checkpoint of `stages` at `path` was trained on (its meta's
    ``trained_on``: data kind, format, path and frame size, frames, steps, and for Stage II how
    the depth network started and Stage I's record), or None when it was not recorded."""
    try:
        return read_meta(find_checkpoint(path, stages)[0]).get("trained_on")
    except CheckpointError as err:
        raise RunError(str(err)) from None


FRAME_SIZE_FACTOR = 2.0
"""An input frame side this many times larger or smaller than the training frames' is far from
what the model saw (its features' scale in pixels changed)."""


def describe_trained_on(trained_on: dict | None) -> str:
    """One line saying what a model was trained on (`read_trained_on`'s record)."""
    if not trained_on:
        return "what it was trained on is not recorded (a checkpoint of an older version)"
    data = trained_on["data"]
    height, width = data["frame_size"]
    steps = ", ".join(f"{phase} {n}" for phase, n in trained_on["steps"].items())
    line = (f"trained on {data['kind']} frames, {height}x{width} ({trained_on['frames']} "
            f"frames of {data['format']} dataset {data['path']}); steps: {steps}")
    network = trained_on.get("depth_network")
    if network:
        line += f"; depth network backbone: {network['backbone']}, head: {network['head']}"
    return line


def input_warnings(trained_on: dict | None, frame_sizes: Collection[tuple[int, int]],
                   data_kind: str = "real") -> list[str]:
    """Lines warning that inputs differ in kind from what the model was trained on: real
    (`data_kind`) frames given to a model trained on synthetic ones only, a frame size more than
    `FRAME_SIZE_FACTOR` from the training frames'."""
    if not trained_on:
        return []
    data = trained_on["data"]
    height, width = data["frame_size"]
    found = []
    if data["kind"] == "synthetic" and data_kind != "synthetic":
        found.append(f"this model was trained on synthetic frames only ({data['path']}); its "
                     "output on real camera frames means nothing: train on real frames (MS2 or "
                     "a folder dataset) first")
    far = sorted({f"{h}x{w}" for h, w in frame_sizes
                  if not (1 / FRAME_SIZE_FACTOR <= h / height <= FRAME_SIZE_FACTOR
                          and 1 / FRAME_SIZE_FACTOR <= w / width <= FRAME_SIZE_FACTOR)})
    if far:
        found.append(f"frames of {', '.join(far)} are far from the {height}x{width} frames the "
                     "model was trained on")
    return found


STALE_STATISTICS = ("its MTSA-UNet's BatchNorm statistics are training's running averages (a "
                    "Stage I finished before phases ended with exact statistics), which cost "
                    "up to 10 dB of reconstruction PSNR")


def stage1_statistics(meta: dict) -> dict | None:
    """How the MTSA-UNet's BatchNorm statistics of the model whose checkpoint meta is `meta`
    were made: a Stage I checkpoint's `FINALIZED` record; a Stage II's, the record of the
    Stage I model it was trained on (``trained_on['stage1_batch_stats']``); None when they are
    training's running averages (a run of an older version)."""
    if str(meta.get("stage", "")).startswith("stage1"):
        return meta.get(FINALIZED)
    return (meta.get("trained_on") or {}).get("stage1_batch_stats")


def statistics_warnings(path: str, meta: dict) -> list[str]:
    """A warning line when the model at `path` (checkpoint meta `meta`) has an MTSA-UNet whose
    BatchNorm statistics are running averages (`stage1_statistics`), with the fix."""
    stage = str(meta.get("stage", ""))
    if stage == "stage2" and not (meta.get("trained_on") or {}).get("stage1"):
        return []  # no Stage I model (e.g. a baseline on tone-mapped frames)
    if stage not in ("stage1_i1", "stage1_i2", "stage2") or stage1_statistics(meta) is not None:
        return []
    fix = (f"train stage1 with `resume` and `workdir` {path} computes them"
           if stage.startswith("stage1")
           else "train it again from that Stage I run resumed once (train stage1 with `resume`)")
    return [f"{path}: {STALE_STATISTICS}; {fix}"]


def load_model(path: str, overrides: Sequence[str] = ()) -> tuple[Config, str, dict]:
    """Loads a trained model for evaluation / prediction.

    Args:
      path: a run's workdir or one of its checkpoint directories.
      overrides: ``key=value`` config overrides (e.g. data.max_depth).
    Returns:
      (config of the run, stage, {'unet': Stage I variables or None, 'depth': Depth Anything V2
      params or None, 'segmentation': what the segmentation branch was trained on, as the
      run recorded it (`load_stage1`), or None, 'trained_on': `read_trained_on`'s record,
      'warnings': `statistics_warnings`}).
    """
    from irdepth_jax.config import apply_overrides

    try:
        directory, stage = find_checkpoint(path)
        meta = read_meta(directory)
        cfg = apply_overrides(from_dict(meta["config"]), list(overrides))
        segmentation = meta.get("segmentation")
        trained_on = meta.get("trained_on")
        warnings = statistics_warnings(path, meta)
        if stage == "stage1_i1":
            segmentation = {"labeled_frames": 0, "why": "Stage I-1 only (no I-2 checkpoint)"}
        if stage.startswith("stage1"):
            items, _ = restore_items(directory, stage, {"model": unet_shapes(cfg)})
            return cfg, stage, {"unet": dict(items["model"]), "depth": None,
                                "segmentation": segmentation, "trained_on": trained_on,
                                "warnings": warnings}
        templates = {"model": {"params": depth_shapes(cfg), "batch_stats": {}}}
        has_unet = cfg.stage2.preprocessing in STAGE1_IMAGES or cfg.stage2.sky_loss
        if has_unet:
            templates["frozen"] = {"unet": unet_shapes(cfg)}
        items, _ = restore_items(directory, stage, templates)
    except CheckpointError as err:
        raise RunError(str(err)) from None
    unet = dict(items["frozen"]["unet"]) if has_unet else None
    return cfg, stage, {"unet": unet, "depth": items["model"]["params"],
                        "segmentation": segmentation, "trained_on": trained_on,
                        "warnings": warnings}
