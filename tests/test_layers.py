"""The code's layers point one way: wire protocols and drivers -> bruce_hw -> runtime -> training, and no two modules
import each other, directly or through others (lazy imports inside functions included)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LAYERS = {"drivers": 0, "bruce_hw": 1, "runtime": 2, "training": 3}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_imports() -> dict[str, list[tuple[str, int]]]:
    """module -> [(imported project module, line)] for every import statement, wherever it is in the file."""
    modules = {module_name(p): p for layer in LAYERS for p in (ROOT / layer).rglob("*.py")}
    graph: dict[str, list[tuple[str, int]]] = {}
    for name, path in modules.items():
        edges = []
        tree = ast.parse(path.read_text(), filename=str(path))
        typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                       and getattr(block.test, "id", None) == "TYPE_CHECKING" for n in ast.walk(block)}
        for node in ast.walk(tree):
            if id(node) in typing_only:  # annotations only: never imported at run time
                continue
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                # `from package import module` imports the module; `from module import name` the module itself
                targets = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                           for alias in node.names]
            else:
                continue
            edges += [(t, node.lineno) for t in targets if t in modules and t != name]
        graph[name] = edges
    return graph


def test_no_layer_imports_a_higher_one():
    upward = [f"{m} (line {line}) imports {t}" for m, edges in project_imports().items() for t, line in edges
              if LAYERS[t.split(".")[0]] > LAYERS[m.split(".")[0]]]
    assert not upward, "imports pointing up a layer:\n" + "\n".join(upward)


def test_no_import_cycles():
    graph = {m: sorted({t for t, _ in edges}) for m, edges in project_imports().items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    cycles = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in graph[module]:
            if state.get(target) == 1:
                cycles.append(" -> ".join(path[path.index(target):] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[module] = 2

    for module in graph:
        if module not in state:
            visit(module, [module])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_walker_sees_imports_inside_functions(tmp_path):
    """The checks above would pass vacuously if the walker missed lazy imports: it must see this project's."""
    edges = project_imports()["runtime.emulate_cli"]
    assert any(t == "bruce_hw.emulation.robot" for t, _ in edges)  # imported inside main()


def _private_members_of_the_mock() -> set[str]:
    """The mock's private attributes and methods: `self._x = ...` in bruce_hw/mock.py and its `def _x` (not the
    lifecycle hooks `_on_*`, `_read`, `_write` that the Backend base calls)."""
    tree = ast.parse((ROOT / "bruce_hw" / "mock.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self" \
                and isinstance(node.ctx, ast.Store) and node.attr.startswith("_"):
            names.add(node.attr)
        if isinstance(node, ast.FunctionDef) and node.name.startswith("_") and not node.name.startswith("__"):
            names.add(node.name)
    return names - {"_read", "_write", "_ground_truth"} - {n for n in names if n.startswith("_on_")}


def test_no_module_outside_the_mock_reads_its_private_state():
    """The tools use the mock's public model and methods (`robot`, `binding`, `model`, `data`, `measure`, `place`);
    the transfer stage and the RL environment build their own `BruceModel`; a subclass may use its own `self._...`."""
    private = _private_members_of_the_mock()
    assert {"_qpos", "_dofs", "_acts"} <= private  # the walker finds them
    found = []
    for layer in (*LAYERS, "bench"):
        for path in (ROOT / layer).rglob("*.py"):
            if path == ROOT / "bruce_hw" / "mock.py":
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Attribute) and node.attr in private and \
                        not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} .{node.attr}")
    assert not found, "\n".join(found)


# Where a whole mock backend is made: the backend table, the emulated robot's plant, and the tools that run whole
# sessions on it (evaluation, distillation, benches of runs). A user that needs only BRUCE's model, its indices or the
# standing placement builds `bruce_hw.robot_model.BruceModel`.
MOCK_MAKERS = {"bruce_hw/mock.py", "bruce_hw/backends.py", "bruce_hw/emulation/plant.py", "training/distill.py",
               "bench/bench_walking_controllers.py", "bench/bench_robot_transfer_cost.py"}


def test_nothing_makes_a_mock_backend_just_for_its_model():
    found = []
    for layer in (*LAYERS, "bench"):
        for path in (ROOT / layer).rglob("*.py"):
            where = path.relative_to(ROOT).as_posix()
            if where in MOCK_MAKERS or where.startswith("training/evaluation/"):
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) \
                        == "MujocoBackend":
                    found.append(f"{where}:{node.lineno}")
    assert not found, "MujocoBackend(...) outside the places that run it (build a BruceModel instead):\n" + \
        "\n".join(found)
