"""The package's layers, read from its imports (module-level and lazy ones inside functions).

The layers, lowest first (docs/architecture.md): physics, atoms, density, the tilt-series
formats (``dataparsers``' readers), the engine (the fit in plain torch), the film, the launch
(what shortens a launcher's start and exit), the nerfstudio layer (with ``dataparsers``'
dataparser and dataset), the API, the harness, the CLI.  A module imports only from its own
layer or lower ones, so there is no import cycle, nerfstudio stays in the nerfstudio layer and
above, and no library module imports the CLI; only the two launchers (the CLI and the
nerfstudio layer) import the launch.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("gaussian_atoms_method", "dataparsers")
LAYERS = ["physics", "atoms", "density", "formats", "engine", "film", "launch", "nerfstudio", "api", "harness", "cli"]


def layer_of(module: str) -> str:
    """The layer a module belongs to (a KeyError for a module outside the layout)."""
    parts = module.split(".")
    if parts[0] == "dataparsers":
        if len(parts) == 1 or parts[1] in (
            "errors",
            "manifest",
            "readers",
            "registration_file",
            "rosetta",
            "stack_data",
            "tilt_series_format",
            "tilt_series_options",
            "views",
        ):
            return "formats"
        if parts[1] == "tilt_series_dataparser":
            return "nerfstudio"
        raise KeyError(module)
    if len(parts) == 1:
        return "api"  # the package's __init__: the API's names, loaded on first use
    sub = {
        "physics": "physics",
        "atoms": "atoms",
        "density": "density",
        "engine": "engine",
        "film": "film",
        "nerfstudio_layer": "nerfstudio",
        "harness": "harness",
        "cli": "cli",
        "api": "api",
        "launch": "launch",
        "parse_errors": "formats",
    }
    return sub[parts[1]]


def package_modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def imports_of(name: str, path: Path, known: set[str]) -> tuple[set[str], bool]:
    """The package modules ``name`` imports anywhere in its file, and whether it imports nerfstudio."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found, nerfstudio = set(), False
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            nerfstudio |= target.split(".")[0] == "nerfstudio"
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found, nerfstudio


@pytest.fixture(scope="module")
def graph():
    modules = package_modules()
    known = set(modules)
    return {name: imports_of(name, path, known) for name, path in modules.items()}


def test_every_module_is_in_a_layer(graph):
    unplaced = []
    for name in graph:
        try:
            layer_of(name)
        except KeyError:
            unplaced.append(name)
    assert not unplaced, (
        f"modules outside the layout (add them to a layer here and in docs/architecture.md): {unplaced}"
    )


def test_imports_only_go_down_the_layers(graph):
    upward = [
        f"{name} ({layer_of(name)}) imports {dep} ({layer_of(dep)})"
        for name, (deps, _) in graph.items()
        for dep in sorted(deps)
        if LAYERS.index(layer_of(dep)) > LAYERS.index(layer_of(name))
    ]
    assert not upward, "\n".join(upward)


def test_no_import_cycles(graph):
    """Tarjan's strongly connected components of the module graph: none of more than one module."""
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v][0]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_nerfstudio_is_imported_only_by_the_nerfstudio_layer_and_above(graph):
    below = [
        name for name, (_, ns) in graph.items() if ns and LAYERS.index(layer_of(name)) < LAYERS.index("nerfstudio")
    ]
    assert not below, f"nerfstudio imported below the nerfstudio layer: {below}"


def test_only_the_launchers_import_the_launch(graph):
    """What shortens a process's start and exit (:mod:`gaussian_atoms_method.launch`) is the two
    command-line launchers' own (``gaussian-atoms train`` and the plugin ``ns-train`` loads):
    the engine takes what they prepared as an argument, and the API never changes a user's
    process to start sooner."""
    launchers = ("launch", "nerfstudio", "cli")
    outside = sorted(
        f"{name} imports {dep}"
        for name, (deps, _) in graph.items()
        for dep in deps
        if layer_of(dep) == "launch" and layer_of(name) not in launchers
    )
    assert not outside, "\n".join(outside)


def test_no_library_module_imports_the_cli(graph):
    outside = [name for name in graph if layer_of(name) != "cli"]
    assert not [name for name in outside if any(layer_of(dep) == "cli" for dep in graph[name][0])]


def test_the_model_stays_thin():
    """The model file holds the model's wiring, rendering and loss; density control, the start,
    convergence and results live in their own modules.  The issue's bound was under 300 lines
    before the code was formatted at 120 columns (ruff); the same file, 290 lines then, holds 209
    statements, so the bound, in a measure the formatter leaves alone, is 216 statements."""
    import ast

    tree = ast.parse((ROOT / "gaussian_atoms_method" / "nerfstudio_layer" / "model.py").read_text())
    statements = sum(isinstance(node, ast.stmt) for node in ast.walk(tree))
    assert statements < 216, f"nerfstudio_layer/model.py has {statements} statements"


def _run(code: str) -> str:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout.strip()


def test_importing_has_no_side_effects():
    """Importing the package loads nothing else; importing the method's config (as ns-train does)
    leaves torch's checkpoint safe-globals alone: the model adds them when it is built."""
    assert (
        _run(
            "import sys, gaussian_atoms_method; print(sorted(m for m in ('torch', 'nerfstudio', 'dataparsers') if m "
            "in sys.modules))"
        )
        == "[]"
    )
    code = (
        "import torch, gaussian_atoms_method.nerfstudio_layer.config; "
        "from gaussian_atoms_method.engine.checkpoints import numpy_checkpoint_globals; "
        "print(sum(g in torch.serialization.get_safe_globals() for g in numpy_checkpoint_globals()))"
    )
    assert _run(code) == "0"


def test_no_library_module_is_over_500_lines():
    """One idea per module: none of the package's modules (the CLI's verbs included) grows past
    500 lines (formatted at 120 columns)."""
    long = {name: path.read_text().count("\n") for name, path in package_modules().items()}
    assert not {name: n for name, n in long.items() if n > 500}


def test_nerfstudio_is_an_adapter_of_seven_modules(graph):
    """The fit is the library and nerfstudio its thin user: only the adapter's modules import
    nerfstudio (the method's config and trainer, the launcher, the model, splatfacto's options
    and properties, the viewer) and the dataparser."""
    importers = sorted(name for name, (_, ns) in graph.items() if ns)
    assert importers == [
        "dataparsers.tilt_series_dataparser",
        "gaussian_atoms_method.nerfstudio_layer.config",
        "gaussian_atoms_method.nerfstudio_layer.launch",
        "gaussian_atoms_method.nerfstudio_layer.model",
        "gaussian_atoms_method.nerfstudio_layer.options",
        "gaussian_atoms_method.nerfstudio_layer.splatfacto_compat",
        "gaussian_atoms_method.nerfstudio_layer.viewer",
    ]


def _reaches_into_others(tree: ast.AST) -> list[str]:
    """What a module's code does to packages it does not own: private names of other packages
    (``pkg._x``, ``from pkg._x import``), assignments to their attributes, entries put into
    ``sys.modules``, and changes to the interpreter's settings (``sys.set*``)."""
    ours = {"gaussian_atoms_method", "dataparsers", "__future__"}
    aliases: dict[str, str] = {}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] not in ours:
                    aliases[a.asname or a.name.split(".")[0]] = a.name
                    if any(p.startswith("_") and not p.startswith("__") for p in a.name.split(".")):
                        found.append(f"line {node.lineno}: import {a.name}")
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] not in ours:
            parts = node.module.split(".") + [a.name for a in node.names]
            if any(p.startswith("_") and not p.startswith("__") for p in parts):
                found.append(f"line {node.lineno}: from {node.module} import {', '.join(a.name for a in node.names)}")

    def root(node):
        chain = []
        while isinstance(node, ast.Attribute):
            chain.append(node.attr)
            node = node.value
        return (node.id if isinstance(node, ast.Name) else None), chain[::-1]

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            name, chain = root(node)
            if name in aliases and any(p.startswith("_") and not p.startswith("__") for p in chain):
                found.append(f"line {node.lineno}: {name}.{'.'.join(chain)}")
        targets = (
            node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AugAssign) else []
        )
        for target in targets:
            name, chain = root(target.value if isinstance(target, ast.Subscript) else target)
            if name in aliases and (chain or isinstance(target, ast.Subscript)):
                found.append(f"line {node.lineno}: assigns {name}.{'.'.join(chain)}")
        if isinstance(node, ast.Call):
            name, chain = root(node.func)
            if name == "sys" and chain and chain[-1].startswith("set"):
                found.append(f"line {node.lineno}: sys.{'.'.join(chain)}")
            if isinstance(node.func, ast.Name) and node.func.id == "setattr" and node.args:
                owner, _ = root(node.args[0])
                if owner in aliases:
                    found.append(f"line {node.lineno}: setattr on {owner}")
    return sorted(set(found))


def test_no_library_module_outside_the_launch_changes_or_reads_into_other_packages():
    """The library leaves a user's process as it found it: outside :mod:`gaussian_atoms_method.launch`
    (the launchers' own processes) no module reads another package's private names, assigns to
    its attributes, puts modules into ``sys.modules`` or changes the interpreter's settings."""
    offences = {
        name: found
        for name, path in package_modules().items()
        if layer_of(name) != "launch" and (found := _reaches_into_others(ast.parse(path.read_text())))
    }
    assert not offences, offences


def test_the_check_for_reaching_into_other_packages_finds_each_kind():
    code = (
        "import sys\nimport torch\nimport numpy as np\nfrom torch._refs import x\n"
        "torch._refs._broadcast_shapes = 1\nnp.float64\nsys.modules['m'] = 1\nsys.setswitchinterval(1)\n"
        "setattr(torch, 'a', 1)\n"
    )
    found = " ".join(_reaches_into_others(ast.parse(code)))
    for kind in ("from torch._refs", "assigns torch._refs._broadcast_shapes", "assigns sys.modules",
                 "sys.setswitchinterval", "setattr on torch"):  # fmt: skip
        assert kind in found, (kind, found)
    assert "np.float64" not in found
