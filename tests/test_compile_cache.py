"""`compile_cache.enable_compilation_cache`: the one setup of JAX's persistent cache (the CLI's
and the experiments'), run in fresh processes so this session's cache stays as it is."""

import os
import pathlib
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import sys
    import jax, jax.numpy as jnp
    from irdepth_jax.compile_cache import enable_compilation_cache
    jax.jit(lambda x: x + 1)(jnp.ones(3))  # a compilation before the cache is set up
    path = None if sys.argv[1] == "off" else sys.argv[1]
    enable_compilation_cache(path, min_compile_time_s=0.0)
    jax.jit(lambda x: jnp.sin(x) * 3)(jnp.ones(5)).block_until_ready()
    print(jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache)
""")


def run(arg: str, env_dir: str | None = None) -> str:
    """SCRIPT's output in a fresh process (JAX_COMPILATION_CACHE_DIR `env_dir`, or unset)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update({"JAX_COMPILATION_CACHE_DIR": env_dir} if env_dir else {})
    done = subprocess.run([sys.executable, "-c", SCRIPT, arg], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_cache_set_up_after_a_compilation_is_written(tmp_path):
    cache = tmp_path / "xla"
    assert run(str(cache)) == f"{cache} True"
    assert cache.is_dir() and any(cache.iterdir())


def test_off_writes_nothing_even_with_the_environment_variable(tmp_path):
    env_cache = tmp_path / "env"
    assert run("off", str(env_cache)) == "None False"
    assert not env_cache.exists() or not any(env_cache.iterdir())


def test_default_dir_is_the_environment_variable_else_home(tmp_path):
    from irdepth_jax.compile_cache import DEFAULT_DIR

    assert pathlib.Path(DEFAULT_DIR).parts[-3:] == (".cache", "irdepth_jax", "xla")
    show = "from irdepth_jax.compile_cache import default_cache_dir; print(default_cache_dir())"
    for env_dir, expected in ((None, DEFAULT_DIR), (str(tmp_path), str(tmp_path))):
        env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
        env.update({"JAX_COMPILATION_CACHE_DIR": env_dir} if env_dir else {})
        done = subprocess.run([sys.executable, "-c", show], env=env, capture_output=True,
                              text=True, timeout=300)
        assert done.stdout.strip() == expected, done.stderr
