"""`irdepth export`: the StableHLO and ONNX artifacts run without irdepth_jax and agree with the
JAX pipeline (`raw_to_depth`) to 1e-4 x max depth, on synthetic and real thermal frames."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from irdepth_jax import cli, export
from irdepth_jax.data.rawio import read_frames
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.models.pipeline import raw_to_depth
from irdepth_jax.runs import variables as model_io

SHAPE = (2, 40, 72)  # export shape: not a multiple of 16, so the UNet's edge padding is in it
REAL_FRAME = "ms2_sample/left/000011_thr.png"  # 256x640, counts 3211-5756


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def model(stage2_run):
    """(config, variables) of the shared Stage II run (conftest), as `irdepth export` loads
    them."""
    cfg, _, variables = model_io.load_model(str(stage2_run))
    return cfg, variables


@pytest.fixture(scope="module", params=["stablehlo", "onnx"])
def exported(request, stage2_run, tmp_path_factory):
    """(format, artifact path, its metadata) of `irdepth export` at `SHAPE`, checked at export
    time on rendered frames."""
    fmt = request.param
    if fmt == "onnx":
        pytest.importorskip("jax2onnx")
        pytest.importorskip("onnxruntime")
    out = tmp_path_factory.mktemp("artifacts") / f"model.{fmt}"
    batch, height, width = SHAPE
    assert cli.main([str(a) for a in ["export", "--checkpoint", stage2_run, "--format", fmt,
                                      "--height", height, "--width", width, "--batch", batch,
                                      "--out", out]]) == 0
    return fmt, out, json.loads(out.with_name(out.name + ".json").read_text())


def run_exported(fmt, path, raw):
    """Runs an artifact as a user would: with JAX alone, or with onnxruntime alone."""
    if fmt == "stablehlo":
        with open(path, "rb") as f:
            return np.asarray(jax.export.deserialize(bytearray(f.read())).call(raw))
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(["depth"], {"raw": raw})[0]


def max_difference(exported, model, raw):
    """max |artifact - raw_to_depth| over raw (N, H, W) uint16, in metres."""
    fmt, path, _ = exported
    cfg, variables = model
    got = run_exported(fmt, path, raw)
    assert got.shape == raw.shape and got.dtype == np.float32
    want = np.asarray(raw_to_depth(variables["unet"], variables["depth"], raw, cfg))
    return float(np.abs(got - want).max())


def test_onnx_opens_without_warnings(exported, capfd):
    """onnxruntime (default log level) opens the ONNX file without a "Removing initializer"
    warning: no (sub)graph keeps a constant no node reads."""
    fmt, path, _ = exported
    if fmt != "onnx":
        pytest.skip("an ONNX file's graph")
    import onnxruntime

    capfd.readouterr()
    onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert "Removing initializer" not in capfd.readouterr().err


def test_synthetic_frames(exported, model):
    cfg, _ = model
    _, height, width = SHAPE
    tolerance = export.TOLERANCE * cfg.depth.max_depth
    # Frames the export-time check did not see, and the edge cases of percentile scaling: a
    # constant frame (zero span) and a ramp over the whole 14-bit range.
    scenes = np.stack([render_scene(7, c, height, width)["raw14"] for c in ("night", "dusk")])
    edges = np.stack([np.full((height, width), 5000, np.uint16),
                      np.linspace(0, 2**14 - 1, height * width).reshape(height, width)
                      .astype(np.uint16)])
    for raw in (scenes, edges):
        assert max_difference(exported, model, raw) <= tolerance
    _, _, meta = exported
    assert meta["input"] == {"name": "raw", "shape": list(SHAPE), "dtype": "uint16",
                             "raw_bits": 14, "range": [0, 2**14 - 1]}
    assert meta["output"] == {"name": "depth", "shape": list(SHAPE), "dtype": "float32",
                              "units": "metres"}
    assert meta["max_depth"] == 80.0 and meta["class_names"][0] == "sky"
    assert meta["config"]["unet"]["raw_scale"] == "percentile"
    assert meta["check"]["sample"] == "synthetic" and meta["check"]["tolerance"] == tolerance
    assert 0 <= meta["check"]["max_abs_diff"] <= tolerance


def test_real_ms2_frame(exported, model, realdata):
    """Two crops (sky and street) of a real MS2 thermal frame, at the export's size."""
    cfg, _ = model
    _, height, width = SHAPE
    [(_, frame)] = read_frames(str(realdata / REAL_FRAME), 14)
    raw = np.stack([frame[:height, 300:300 + width], frame[-height:, 100:100 + width]])
    assert max_difference(exported, model, raw) <= export.TOLERANCE * cfg.depth.max_depth


def test_sample_file_and_refusals(stage1_run, stage2_run, model, tmp_path, capsys,
                                  monkeypatch):
    batch, height, width = SHAPE
    out = tmp_path / "m.stablehlo"
    args = ["export", "--checkpoint", stage2_run, "--format", "stablehlo", "--height",
            height, "--width", width, "--batch", batch, "--out", out]
    stack = tmp_path / "frames.npy"  # one frame: cycled to the batch
    np.save(stack, render_scene(3, "day", height, width)["raw14"][None])
    code, stdout, err = run(args + ["--sample", stack], capsys)
    assert code == 0, err
    meta = json.loads((tmp_path / "m.stablehlo.json").read_text())
    assert meta["check"]["sample"] == str(stack)
    assert stdout.splitlines() == [
        (f"max |stablehlo - JAX| = {meta['check']['max_abs_diff']:.3g} m on {batch} sample "
         f"frames (tolerance {meta['check']['tolerance']:.3g} m)"),
        f"wrote {out} and {out}.json"]

    def one_line_error(argv, *needles):
        code, _, err = run(argv, capsys)
        lines = [ln for ln in err.strip().splitlines() if ln.startswith("irdepth")]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("irdepth: error: "), err
        assert all(n in lines[0] for n in needles), lines[0]

    one_line_error(args[:-1] + [tmp_path], "--out", str(tmp_path), "directory")
    one_line_error(args + ["--batch", "0"], "--batch 0")
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((height, width + 1), np.uint16))
    one_line_error(args + ["--sample", wrong], str(wrong), f"{height}x{width + 1}",
                   f"{height}x{width}")
    one_line_error([stage1_run if a == stage2_run else a for a in args],
                   str(stage1_run), "Stage I model")
    # an artifact that disagrees with JAX is refused, and nothing is written
    out.unlink(), (tmp_path / "m.stablehlo.json").unlink()
    monkeypatch.setattr(export, "run_artifact", lambda fmt, data, raw: np.full(raw.shape, 1e3))
    one_line_error(args, "differs from the JAX pipeline", "nothing written")
    assert not out.exists() and not (tmp_path / "m.stablehlo.json").exists()
    # tone-mapping baselines are host (NumPy / OpenCV) code: refused by name
    cfg, variables = model
    he = dataclasses.replace(cfg, stage2=dataclasses.replace(cfg.stage2, preprocessing="he"))
    with pytest.raises(export.ExportError, match="preprocessing=he: .* only models whose input the Stage I"):
        export.depth_function(he, variables, "RUN")
    # onnxruntime's CPU kernels take no bfloat16 Einsum: such a model is refused before converting
    bf16 = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, dtype="bfloat16"))
    monkeypatch.setattr(model_io, "load_model", lambda path: (bf16, "stage2", variables))
    with pytest.raises(export.ExportError, match="depth.dtype=bfloat16, .* use `format` stablehlo"):
        export.export_model("RUN", "onnx", height, width, batch, str(out))
    # on a GPU a bfloat16 model's attention is cuDNN's fused kernel, which the artifact cannot hold
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with pytest.raises(export.ExportError, match=r"cuDNN's fused kernel: .*\(JAX_PLATFORMS=cpu\)"):
        export.export_model("RUN", "stablehlo", height, width, batch, str(out))
