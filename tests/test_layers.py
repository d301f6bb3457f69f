"""The package's data flow is one way (docs/architecture.md): no module imports one of a later
layer, at the top of the file, inside a function or by `importlib.import_module` with a literal
package path (an f-string's literal head: ``f"irdepth_jax.configs.{name}"`` imports every
module of `configs`), and there is no import cycle."""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "irdepth_jax"

LAYERS = [
    ("foundation", ["config_schema", "configs", "config", "errors", "fileio", "video", "compile_cache",
                    "program_cache", "hostmem"]),
    ("imaging", ["imaging"]),
    ("models", ["models", "weights"]),
    ("CPU training kernels", ["xla_cpu"]),
    ("losses and metrics", ["losses", "metrics", "image_metrics"]),
    ("data", ["data"]),
    ("run directories and checkpoints", ["runs"]),
    ("training mechanics", ["train", "train.state", "train.steps", "train.parallel", "train.workdir_lock",
                            "train.runlog"]),
    ("evaluators", ["evaluators"]),
    ("training loops", ["train.phase", "train.validate", "train.stages"]),
    ("runs and deployment", ["evaluate", "predict", "predict_settings", "predict_runner",
                             "predict_outputs", "predict_video", "pointcloud",
                             "depth_colours", "export", "workflow"]),
    ("command line", ["cli", "__main__"]),
]


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> int | None:
    """Index in LAYERS of a module (dotted, without 'irdepth_jax.'): its longest listed prefix."""
    best, index = -1, None
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, index = len(prefix), i
    return index


def imports(path: pathlib.Path) -> set[str]:
    """Package modules `path` imports anywhere in the file (dotted, without 'irdepth_jax.')."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "irdepth_jax":
                found.update(alias.name for alias in node.names)
            elif node.module.startswith("irdepth_jax."):
                base = node.module[len("irdepth_jax."):]
                for alias in node.names:  # `from irdepth_jax.train import phase` is a module
                    child = PACKAGE.joinpath(*base.split("."), alias.name)
                    sub = child.with_suffix(".py").exists() or child.is_dir()
                    found.add(f"{base}.{alias.name}" if sub else base)
        elif isinstance(node, ast.Import):
            found.update(a.name[len("irdepth_jax."):] for a in node.names
                         if a.name.startswith("irdepth_jax."))
        elif isinstance(node, ast.Call) and _is_import_module(node.func) and node.args:
            target = _literal_head(node.args[0])
            if target.startswith("irdepth_jax."):
                found.add(target[len("irdepth_jax."):])
    return found


def expand(deps: set[str], modules: set[str]) -> set[str]:
    """`deps` with each ``X.*`` (an importlib load of any module of X) as X and its modules."""
    out = set()
    for dep in deps:
        if dep.endswith(".*"):
            base = dep[:-2]
            out |= {base} | {m for m in modules if m.startswith(base + ".")}
        else:
            out.add(dep)
    return out


def _is_import_module(func: ast.expr) -> bool:
    """`importlib.import_module` or a bare `import_module`."""
    return (isinstance(func, ast.Attribute) and func.attr == "import_module") or (
        isinstance(func, ast.Name) and func.id == "import_module")


def _literal_head(arg: ast.expr) -> str:
    """The module path a call imports, as far as it is literal: a string constant whole; an
    f-string ``'P.{...}'`` as ``P.*`` (any module of P); '' otherwise."""
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        return str(arg.values[0].value).rstrip(".") + ".*"
    return ""


def graph() -> dict[str, set[str]]:
    found = {module_name(p): imports(p) for p in PACKAGE.rglob("*.py")}
    return {module: expand(deps, set(found)) for module, deps in found.items()}


def test_every_module_has_a_layer():
    assert [m for m in graph() if m and layer_of(m) is None] == []


def test_no_module_imports_a_later_layer():
    upward = []
    for module, deps in graph().items():
        if not module:
            continue
        for dep in deps:
            if layer_of(dep) is not None and layer_of(dep) > layer_of(module):
                upward.append(f"{module} ({LAYERS[layer_of(module)][0]}) imports {dep} "
                              f"({LAYERS[layer_of(dep)][0]})")
    assert upward == []


def test_no_import_cycle():
    edges = graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        for dep in sorted(edges.get(node, ())):
            dep = dep if dep in edges else dep.rsplit(".", 1)[0]
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep):] + [dep])
            elif dep in edges and not state.get(dep):
                visit(dep, stack + [dep])
        state[node] = 2

    for module in sorted(edges):
        if not state.get(module):
            visit(module, [module])
    # a package's __init__ importing its own submodules is not a cycle of ours
    assert [c for c in cycles if len(set(c)) > 1 and "" not in c] == []


def test_the_checker_sees_importlib_loads(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("import importlib\nfrom importlib import import_module\n"
                      "def f(name):\n    importlib.import_module(f'irdepth_jax.configs.{name}')\n"
                      "    import_module('irdepth_jax.train.phase')\n    importlib.import_module(name)\n")
    assert imports(source) == {"configs.*", "train.phase"}
    assert expand(imports(source), {"configs.tiny", "train.phase"}) == {"configs", "configs.tiny", "train.phase"}


def test_config_loads_the_presets_and_they_do_not_import_it():
    edges = graph()
    assert {"configs", "configs.tiny", "configs.paper"} <= edges["config"]  # get_config's importlib load
    assert all("config" not in deps for module, deps in edges.items() if module.startswith("configs"))


def test_the_checker_sees_function_level_imports(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from irdepth_jax.cli import main\n    from irdepth_jax.train "
                      "import phase\n")
    assert imports(source) == {"cli", "train.phase"}
