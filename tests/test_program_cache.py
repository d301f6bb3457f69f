"""`program_cache`: a warm start reads the models' shapes and the exported pipeline instead of
tracing them, computes what the traced program computes, and never serves an entry made by other
source code or for other arguments."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax import program_cache
from irdepth_jax.compile_cache import enable_compilation_cache
from irdepth_jax.config import apply_overrides, get_config, to_dict
from irdepth_jax.runs.variables import depth_shapes, init_unet, random_depth

CFG = apply_overrides(get_config("tiny"), ["stage2.preprocessing=he", "stage2.sky_loss=false"])


@pytest.fixture
def cache_dir(tmp_path):
    """The compilation cache (and so the program cache) in `tmp_path` for one test."""
    before = jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache
    enable_compilation_cache(str(tmp_path / "xla"))
    yield tmp_path / "xla-programs"
    enable_compilation_cache(before[0] if before[1] else None)


def test_shapes_are_traced_once_then_read(cache_dir, monkeypatch):
    made = []

    def make():
        made.append(1)
        return jax.eval_shape(lambda: init_unet(CFG))

    first = program_cache.cached_shapes("unet_shapes", to_dict(CFG), make)
    again = program_cache.cached_shapes("unet_shapes", to_dict(CFG), make)
    assert len(made) == 1 and jax.tree.structure(again) == jax.tree.structure(first)
    assert jax.tree.leaves(again) == jax.tree.leaves(first)  # shapes and dtypes
    other = apply_overrides(CFG, ["seed=5"])
    program_cache.cached_shapes("unet_shapes", to_dict(other), make)
    assert len(made) == 2  # another config: another entry
    monkeypatch.setattr(program_cache, "source_digest", lambda: "other source")
    program_cache.cached_shapes("unet_shapes", to_dict(CFG), make)
    assert len(made) == 3  # another source: another entry
    for entry in cache_dir.iterdir():
        entry.write_text("{damaged")
    program_cache.cached_shapes("unet_shapes", to_dict(CFG), make)
    assert len(made) == 4  # a damaged entry is made again
    assert depth_shapes(CFG) == jax.eval_shape(lambda: random_depth(CFG))  # the library's use


def test_exported_program_is_read_and_computes_what_the_traced_one_does(cache_dir):
    @jax.jit
    def fn(x, scale=None):
        return {"y": jnp.tanh(x) * scale, "none": None}

    x, scale = jnp.arange(6.0).reshape(2, 3), jnp.float32(3.0)
    assert program_cache.kept_export("fn", {"k": 1}, (x,), {"scale": scale}) is None
    program_cache.keep_export("fn", {"k": 1}, jax.export.export(fn)(x, scale=scale), (x,), {"scale": scale})
    kept = program_cache.kept_export("fn", {"k": 1}, (x,), {"scale": scale})
    out = jax.jit(kept.call)(x, scale=scale)
    np.testing.assert_array_equal(np.asarray(out["y"]), np.asarray(fn(x, scale=scale)["y"]))
    assert out["none"] is None
    assert program_cache.kept_export("fn", {"k": 1}, (x[:1],), {"scale": scale}) is None  # another shape
    assert program_cache.kept_export("fn", {"k": 2}, (x,), {"scale": scale}) is None  # made from other
    for entry in cache_dir.glob("*.jaxexport"):
        entry.write_bytes(b"damaged")
    assert program_cache.kept_export("fn", {"k": 1}, (x,), {"scale": scale}) is None


def test_off_without_the_compilation_cache(tmp_path):
    before = jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache
    enable_compilation_cache(None)
    try:
        assert program_cache.directory() is None
        made = []
        tree = {"a": jax.ShapeDtypeStruct((1,), jnp.float32)}
        for _ in range(2):
            program_cache.cached_shapes("s", {}, lambda: made.append(1) or tree)
        assert len(made) == 2
    finally:
        enable_compilation_cache(before[0] if before[1] else None)


def test_predictor_from_the_program_cache_matches_run_pipeline(cache_dir, monkeypatch):
    """`irdepth predict`'s model side: a second Predictor (a warm start) traces no pipeline, its
    compile is read from JAX's persistent cache (the first start compiled the exported program
    itself), and its depth equals `run_pipeline`'s."""
    from irdepth_jax import predict_runner
    from irdepth_jax.models import pipeline

    enable_compilation_cache(str(cache_dir.parent / "xla"), min_compile_time_s=0.0)  # every compile kept
    model = {"unet": None, "depth": random_depth(CFG)}
    raw = np.random.default_rng(0).integers(0, 2**14, (1, 32, 48)).astype(np.uint16)
    predict_runner.Predictor(CFG, model, 14).dispatch(raw)
    traces, events = [], []
    original = pipeline.pipeline_outputs
    monkeypatch.setattr(pipeline, "pipeline_outputs", lambda *a, **k: traces.append(1) or original(*a, **k))

    def listen(event, **_):
        events.append(event)
    jax.monitoring.register_event_listener(listen)
    try:
        depth = np.asarray(predict_runner.Predictor(CFG, model, 14).dispatch(raw)["depth"])
    finally:
        jax.monitoring.unregister_event_listener(listen)
    assert traces == []
    assert "/jax/compilation_cache/cache_hits" in events
    assert "/jax/compilation_cache/cache_misses" not in events
    monkeypatch.undo()
    from irdepth_jax.data.source import host_image

    image = jnp.asarray(host_image({"raw14": raw}, "he"))
    expected = pipeline.run_pipeline(None, model["depth"], None, CFG, image=image)
    np.testing.assert_allclose(depth, np.asarray(expected["depth"]), rtol=1e-6, atol=1e-6)


def test_a_pipeline_jax_cannot_export_is_compiled_by_the_plain_jit(cache_dir, monkeypatch):
    """A program with a custom call that has no compatibility guarantee (cuDNN's fused
    attention of a bfloat16 ViT on a GPU) cannot be exported: `irdepth predict` then compiles
    `run_pipeline` itself, keeps nothing, and gives its depth; another ValueError still raises."""
    from irdepth_jax import predict_runner
    from irdepth_jax.data.source import host_image
    from irdepth_jax.models import pipeline

    def refuse(_fn):
        def export(*_args, **_kwargs):
            raise ValueError("Cannot serialize code with custom calls whose targets have no "
                             "compatibility guarantees. Examples are: __cudnn$fmhaSoftmax")
        return export

    monkeypatch.setattr(jax.export, "export", refuse)
    model = {"unet": None, "depth": random_depth(CFG)}
    raw = np.random.default_rng(0).integers(0, 2**14, (1, 32, 48)).astype(np.uint16)
    predictor = predict_runner.Predictor(CFG, model, 14)
    depth = np.asarray(predictor.dispatch(raw)["depth"])
    args, kwargs = predictor._arguments(raw)
    assert program_cache.kept_export("pipeline", to_dict(CFG), args, kwargs) is None
    image = jnp.asarray(host_image({"raw14": raw}, "he"))
    expected = pipeline.run_pipeline(None, model["depth"], None, CFG, image=image)
    np.testing.assert_allclose(depth, np.asarray(expected["depth"]), rtol=1e-6, atol=1e-6)

    def broken(_fn):
        def export(*_args, **_kwargs):
            raise ValueError("something else")
        return export

    monkeypatch.setattr(jax.export, "export", broken)
    with pytest.raises(ValueError, match="something else"):
        predict_runner.Predictor(CFG, model, 14).dispatch(raw)
