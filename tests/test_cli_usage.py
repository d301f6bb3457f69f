"""Usage errors are reported at once: checked before JAX is imported or a model is loaded."""

import os
import subprocess
import sys
import time

import pytest

PROBE = """
import sys
from irdepth_jax import cli
code = cli.main(sys.argv[1:])
print("jax imported" if "jax" in sys.modules else "jax not imported", code)
"""


def irdepth(*argv):
    """(exit code line, stderr, seconds) of `irdepth ARGV` in a fresh interpreter."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", PROBE, *map(str, argv)], capture_output=True,
                          text=True, env=env, timeout=120)
    return proc.stdout.strip(), proc.stderr.strip(), time.perf_counter() - start


@pytest.mark.parametrize("argv, message", [
    (["predict", "--checkpoint", "{tmp}", "--out", "{tmp}/o", "{tmp}/nonexistent.png"],
     "{tmp}/nonexistent.png: no such file or directory"),
    (["predict", "--checkpoint", "{tmp}/nothing", "--out", "{tmp}/o", "{tmp}"],
     "--checkpoint {tmp}/nothing: no such file or directory"),
    (["predict", "--checkpoint", "{tmp}", "--out", "{tmp}/o", "--depth-png", "{tmp}"],
     "--depth-png adds per-frame depth PNGs to --video"),
    (["eval", "--workdir", "{tmp}", "--data", "{tmp}/no_data"],
     "--data {tmp}/no_data: no such file or directory"),
    (["export", "--checkpoint", "{tmp}/none", "--format", "onnx", "--height", "8", "--width", "8",
      "--out", "{tmp}/m.onnx"], "--checkpoint {tmp}/none: no such file or directory"),
    (["train", "stage2", "--data", "{tmp}", "--workdir", "{tmp}/w", "--stage1-checkpoint",
      "{tmp}/s1"], "--stage1-checkpoint {tmp}/s1: no such file or directory"),
])
def test_usage_errors_come_before_jax(tmp_path, argv, message):
    out, err, seconds = irdepth(*[a.format(tmp=tmp_path) for a in argv])
    assert out == "jax not imported 2", (out, err)
    assert err.startswith(f"irdepth: error: {message.format(tmp=tmp_path)}"), err
    assert len(err.splitlines()) == 1
    assert seconds < 3, seconds


def test_synth_defaults_fit_any_n(tmp_path, capsys):
    """--labeled defaults to half of --n (a fixed 48 exceeded --n 4); counts read as English;
    errors name flags, not API keywords."""
    from irdepth_jax import cli

    out = tmp_path / "d"
    assert cli.main(["synth", "--out", str(out), "--n", "4", "--size", "16x24",
                     "--no-progress"]) == 0
    assert "wrote 4 frames (2 labelled, 16x24, street scenes)" in capsys.readouterr().out
    assert cli.main(["synth", "--out", str(tmp_path / "one"), "--n", "1", "--size", "16x24",
                     "--no-progress"]) == 0
    assert "wrote 1 frame (0 labelled" in capsys.readouterr().out
    for argv, message in (
            (["--out", str(out), "--n", "4"],
             f"--out {out}: directory exists and is not empty; choose another path, or pass "
             "--overwrite to replace the dataset"),
            (["--out", str(tmp_path / "e"), "--n", "4", "--labeled", "5"],
             "--labeled 5: choose 0 to --n (4)")):
        assert cli.main(["synth", *argv, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.strip() == f"irdepth: error: {message}", err
    assert not (tmp_path / "e").exists()


def test_a_bad_config_value_is_one_line_naming_the_key(tmp_path, capsys):
    """A value outside a key's set is refused before anything is written, naming the key and
    the values it takes, exit code 2."""
    from irdepth_jax import cli

    work = tmp_path / "w"
    code = cli.main(["train", "stage1", "--data", str(tmp_path), "--workdir", str(work),
                     "stage2.hue_mode=hsv"])
    assert code == 2
    assert capsys.readouterr().err == ("irdepth: error: stage2.hue_mode='hsv': choose one of soft, "
                                       "argmax, constant\n")
    assert not work.exists()


def test_a_bug_is_not_reported_as_a_usage_error(tmp_path, capsys, monkeypatch):
    """Only the package's own errors are one-line usage errors: a plain ValueError raised inside
    the library (a bug) propagates with its traceback."""
    from irdepth_jax import cli, config

    def planted(*args, **kwargs):
        raise ValueError("planted bug")

    monkeypatch.setattr(config, "apply_overrides", planted)
    with pytest.raises(ValueError, match="planted bug"):
        cli.main(["train", "stage1", "--data", str(tmp_path), "--workdir", str(tmp_path / "w")])
    assert "irdepth: error" not in capsys.readouterr().err


def test_library_errors_name_options_the_cli_shows_as_flags():
    from irdepth_jax.cli import build_parser
    from irdepth_jax.errors import with_flags

    args = build_parser().parse_args(["train", "stage2", "--data", "d", "--workdir", "w"])
    message = "`stage1_checkpoint` x: no; pass `resume_or_start` or `resume` (`nothing`)"
    assert with_flags(message, args.flags) == ("--stage1-checkpoint x: no; pass --resume-or-start "
                                               "or --resume (`nothing`)")


FLAGS_STILL_NAMED = {"predict.py", "predict_runner.py", "predict_video.py", "data/inputs.py", "data/rosbag.py",
                     "imaging/raw.py"}
"""Modules whose messages still name predict's flags: predict prints them itself as skip lines,
not through `cli.main`, which writes the library's `name`s as flags."""


def test_library_messages_name_options_not_flags():
    """Outside the CLI, a message names an option as `name` (errors.py), never as --flag (the
    strings of the package's modules but docstrings, which may say which flag uses a function;
    a compiler's --version is no flag of ours)."""
    import ast
    import pathlib
    import re

    package = pathlib.Path(__file__).resolve().parents[1] / "irdepth_jax"
    flag = re.compile(r"(^|[\s(])--[a-z]")
    found = []
    for path in sorted(package.rglob("*.py")):
        name = path.relative_to(package).as_posix()
        if name.startswith("cli/") or name in FLAGS_STILL_NAMED:
            continue
        tree = ast.parse(path.read_text())
        docstrings = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr)}
        found += [f"{name}:{c.lineno}: {c.value}" for c in ast.walk(tree)
                  if isinstance(c, ast.Constant) and isinstance(c.value, str)
                  and id(c) not in docstrings and flag.search(c.value) and c.value != "--version"]
    assert not found, found


def test_quickstart_refuses_a_used_workdir_before_jax(tmp_path):
    (tmp_path / "mine.txt").write_text("keep me")
    out, err, _ = irdepth("quickstart", "--workdir", tmp_path)
    assert out == "jax not imported 2", (out, err)
    assert err == f"irdepth: error: --workdir {tmp_path} exists and is not empty; choose another directory"
    assert os.listdir(tmp_path) == ["mine.txt"]
