"""The structure holds: every import points down the layers, no cycles, small files.

Read from the source (ast), nothing is imported: the layers of docs/development.md's
layout, the import graph of files and packages, function-local imports of the project, and
the sizes the next engineer can hold in mind (functions <= 120 lines, files <= 700 lines).
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The installed packages, and the workshop (tools/: the fault-injection kit and the
#: developer scripts, not installed), held to the same structure.
PROJECT = ('gnsscam_ros', 'msg_adapters', 'tools')
#: Bottom first; a package may import only packages before it (and itself). The workshop
#: is last: nothing of the product may import it.
LAYERS = ('gnsscam_ros.core', 'gnsscam_ros.io', 'msg_adapters', 'gnsscam_ros.vision',
          'gnsscam_ros.datasets', 'gnsscam_ros.bags', 'gnsscam_ros.nodes', 'gnsscam_ros.live',
          'gnsscam_ros.evaluation', 'gnsscam_ros.bench', 'tools')
MAX_LOCAL_IMPORTS, MAX_FUNCTION_LINES, MAX_FILE_LINES = 5, 120, 700


def modules() -> dict[str, Path]:
    out = {}
    for top in PROJECT:
        for path in (ROOT / top).rglob('*.py'):
            parts = list(path.relative_to(ROOT).with_suffix('').parts)
            if parts[-1] == '__init__':
                parts = parts[:-1]
            out['.'.join(parts)] = path
    return out


MODULES = modules()


def imports(name: str, path: Path) -> list[tuple[str, bool, int]]:
    """``(imported project module, inside a function, line)`` of one module."""
    tree = ast.parse(path.read_text())
    package = name if path.name == '__init__.py' else name.rsplit('.', 1)[0]
    local = {id(n) for f in ast.walk(tree)
             if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
             for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parts = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(parts + ([base] if base else []))
            targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in MODULES else base
                       for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES and '.' in target:
                target = target.rsplit('.', 1)[0]
            if target in MODULES and target != name:
                out.append((target, id(node) in local, node.lineno))
    return out


GRAPH = {name: imports(name, path) for name, path in MODULES.items()}


def layer_of(name: str) -> str:
    return next(layer for layer in LAYERS if name == layer or name.startswith(layer + '.'))


def test_every_module_sits_in_a_layer():
    assert all(layer_of(name) for name in MODULES if name not in PROJECT)


def test_imports_point_down_the_layers():
    upward = []
    for name, targets in GRAPH.items():
        if name in PROJECT:
            continue
        mine = LAYERS.index(layer_of(name))
        for target, _, line in targets:
            if target not in PROJECT and LAYERS.index(layer_of(target)) > mine:
                upward.append(f'{MODULES[name].relative_to(ROOT)}:{line} -> {target}')
    assert not upward, upward


def test_no_file_import_cycles():
    edges = {name: {t for t, _, _ in targets} for name, targets in GRAPH.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            # A package's __init__ re-exporting its own modules is not a cycle of files.
            if node in PROJECT or nxt.startswith(node + '.'):
                continue
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for name in sorted(edges):
        if name not in state:
            visit(name, [name])
    assert not cycles, cycles


def test_few_function_local_imports_of_the_project():
    local = [f'{MODULES[name].relative_to(ROOT)}:{line} {target}'
             for name, targets in GRAPH.items() for target, inside, line in targets if inside]
    assert len(local) <= MAX_LOCAL_IMPORTS, local


def test_functions_and_files_stay_small():
    long_functions, long_files = [], []
    for name, path in MODULES.items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_FILE_LINES:
            long_files.append(str(path.relative_to(ROOT)))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f'{path.relative_to(ROOT)}:{node.name} {length}')
    assert not long_files, long_files
    assert not long_functions, long_functions


#: Packages that consume the epoch engine: they take its reports, never its filter.
ENGINE_CONSUMERS = ('gnsscam_ros.nodes', 'gnsscam_ros.live', 'gnsscam_ros.evaluation',
                    'gnsscam_ros.bench')


def test_consumers_of_the_engine_never_reach_into_its_filter():
    """The epoch's outputs are the engine's report (``EpochReport``) and the engine's own
    attributes; an ``x.filter`` attribute in a consumer reads past them."""
    reaching = []
    for name, path in MODULES.items():
        if not name.startswith(ENGINE_CONSUMERS):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == 'filter':
                reaching.append(f'{path.relative_to(ROOT)}:{node.lineno}')
    assert not reaching, reaching
