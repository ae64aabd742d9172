"""The core reads as the method, in layers: each concept a sub-package, every import of another
core package pointing to a lower layer, and no flat list of modules longer than a reader takes
in at a glance."""
import ast
import pkgutil
from pathlib import Path

import meshfg_ros.core

CORE = Path(meshfg_ros.core.__path__[0])
# The rank of each part of the core: a module may import its own part and parts of lower rank.
# geometry and solvers know nothing of each other; the scheduler sits on everything; settings
# and worker_threads serve every part.
RANKS = {"settings": 0, "worker_threads": 0, "geometry": 1, "solvers": 1, "inputs": 2, "physics": 3, "estimation": 4, "scheduler": 5}
MAX_MODULES_PER_LEVEL = 8


def _part(module: str) -> str:
    """The part of the core a dotted module name (meshfg_ros.core.<part>[.<module>]) belongs to."""
    return module.split(".")[2]


def _core_imports(path: Path) -> set[str]:
    """The meshfg_ros.core modules and packages the file imports."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("meshfg_ros.core."):
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names if alias.name.startswith("meshfg_ros.core."))
    return names


def test_every_part_of_the_core_has_a_rank():
    parts = {info.name for info in pkgutil.iter_modules([str(CORE)])}
    assert parts == set(RANKS), sorted(parts ^ set(RANKS))


def test_imports_run_from_higher_layers_to_lower_ones():
    wrong = []
    for path in CORE.rglob("*.py"):
        relative = path.relative_to(CORE).with_suffix("")
        if relative.parts[0] == "__init__":
            continue
        own = relative.parts[0]
        for imported in _core_imports(path):
            target = _part(imported)
            if target != own and RANKS[target] >= RANKS[own]:
                wrong.append(f"{path.relative_to(CORE)} imports {imported}")
    assert not wrong, wrong


def test_no_level_of_the_core_is_a_long_flat_list():
    for folder in [CORE, *(p for p in CORE.iterdir() if (p / "__init__.py").is_file())]:
        modules = [p for p in folder.glob("*.py") if p.name != "__init__.py"]
        assert len(modules) <= MAX_MODULES_PER_LEVEL, (folder, sorted(p.name for p in modules))
