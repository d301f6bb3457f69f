"""The first GPU run's script (experiments/gpu_run.sh) runs end to end on a CPU in its dry-run
mode (tiny shapes), so that scarce GPU minutes are not spent on a typo; and its table
says what has not been measured on a GPU."""

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("torch", reason="the official side needs torch (the [parity] extra)")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_table_without_results_says_not_measured(tmp_path):
    from irdepth_experiments.gpu_run import NOT_MEASURED, main

    main(["table", "--out", str(tmp_path)])
    table = (tmp_path / "gpu.md").read_text()
    assert table.count(NOT_MEASURED) == 4 and "DRY RUN" not in table


def test_gpu_part_refuses_without_a_gpu(tmp_path):
    from irdepth_experiments.gpu_run import main

    with pytest.raises(SystemExit, match="no GPU"):
        main(["stage1", "--out", str(tmp_path)])


def test_dry_run_end_to_end(tmp_path):
    from irdepth_experiments.bench_depth_anything import official_code_present

    # the script's `python` is the one running this suite
    path = os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", "")])
    env = {**os.environ, "OUT": str(tmp_path), "PYTHONPATH": ROOT, "PATH": path}
    run = subprocess.run(["bash", os.path.join(ROOT, "experiments", "gpu_run.sh"), "dry"], env=env,
                         capture_output=True, text=True, timeout=1800)
    assert run.returncode == 0, run.stderr[-3000:]
    stage2 = json.loads((tmp_path / "stage2_vits.json").read_text())
    stage1 = json.loads((tmp_path / "stage1_predict.json").read_text())
    assert stage2["dry_run"] and stage2["ours_images_per_s"] > 0 and stage2["reference_images_per_s"] > 0
    # as on the GPU: against the official code where its checkout is, else transformers' port
    assert stage2["reference"] == ("official" if official_code_present() else "transformers")
    assert (stage2["dtype"], stage2["torch_autocast_bf16"]) == ("bfloat16", True)
    assert stage2["ours_mfu_measured_peak"] > 0 and stage2["step_gflop"] > 0
    assert stage1["stage1"]["images_per_s"] > 0 and stage1["predict"]["frames_per_s"] > 0
    assert stage1["predict"]["depth_dtype"] == "bfloat16"
    table = (tmp_path / "gpu.md").read_text()
    assert "DRY RUN" in table and "not yet measured" not in table
