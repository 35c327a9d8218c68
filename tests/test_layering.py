"""The layering of the packages, read from their imports and checked in fresh interpreters.

- protocol (the contract) imports nothing of the project, and none of its modules imports
  Gymnasium, PettingZoo, Zenoh or ctypes; envs (the faces) and ipc (Zenoh, shared memory) import
  only protocol; cli (the commands' one door) only protocol; viz only protocol and cli;
- server never imports client or trainers; client never imports server or trainers; trainers
  never import server (a trainer must work against a simulator on another machine);
- the simulation core (overtake.server.sim) imports numpy and the standard library only, and of
  the project only the contract's vocabulary: importing it loads no msgpack, Zenoh, Gymnasium,
  Rerun or PyTorch;
- importing overtake.protocol loads neither Zenoh nor Rerun (nor msgpack nor Gymnasium, which
  load on first use), importing overtake.viz no Rerun;
- the Gymnasium ids are registered by ``import overtake.client`` and by nothing else;
- Ray is imported by overtake-experiment's Ray launcher only, and an experiment without
  ``--ray`` loads none of it;
- envs names no simulator setting, and trainers switch no sensor and set no ego field by its
  setting's name: they ask by the open request's typed fields.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {
    "protocol": "protocol",
    "envs": "envs",
    "ipc": "ipc",
    "cli": "cli",
    "viz": "viz",
    "server": "server",
    "client": "client",
    "trainers": "trainers",
}
# The parts of the project each package may import (besides itself).
ALLOWED = {
    "protocol": set(),
    "envs": {"protocol"},
    "ipc": {"protocol"},
    "cli": {"protocol"},
    "viz": {"protocol", "cli"},
    "server": {"protocol", "envs", "ipc", "cli", "viz"},
    "client": {"protocol", "envs", "ipc", "cli", "viz"},
    # The faces (envs) are Gymnasium's, whichever engine is under them; a trainer never
    # reaches the simulator (server) or the wire's mechanism (ipc) itself.
    "trainers": {"protocol", "envs", "cli", "viz", "client"},
}
HEAVY = ("msgpack", "zenoh", "gymnasium", "rerun", "torch")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(["overtake", *parts])


def _imports(path: Path) -> list[tuple[str, int]]:
    """Every module ``path`` imports (absolute names), anywhere in the file, with line numbers."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((name, node.lineno))
            # `from . import x` and `from pkg import submodule` name modules too.
            found += [(f"{name}.{alias.name}", node.lineno) for alias in node.names]
    return found


def _sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_each_folder_is_its_overtake_package_and_nothing_else_is():
    """pyproject maps each folder to ``overtake.<name>``, and a fresh interpreter (run from
    elsewhere than the checkout) imports each from its folder; ``import <folder>`` alone
    finds nothing: user code never writes ``import client``."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    mapped = project["tool"]["setuptools"]["package-dir"]
    assert mapped == {f"overtake.{name}": folder for name, folder in FOLDERS.items()}
    probe = (
        "import importlib, importlib.util, json\n"
        f"names = {sorted(FOLDERS)!r}\n"
        "print(json.dumps({\n"
        "    'files': {n: importlib.import_module('overtake.' + n).__file__ for n in names},\n"
        "    'bare': [n for n in names if importlib.util.find_spec(n) is not None],\n"
        "}))\n"
    )
    found = _probe(probe, Path("/"))
    for name, folder in FOLDERS.items():
        assert _sources(folder), f"no Python files under {folder}/"
        assert Path(found["files"][name]).resolve() == (ROOT / folder / "__init__.py").resolve()
    assert found["bare"] == [], f"importable without overtake.: {found['bare']}"


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_each_package_imports_only_the_parts_below_it(package):
    wrong = []
    for path in _sources(FOLDERS[package]):
        for name, line in _imports(path):
            parts = name.split(".")
            if parts[0] != "overtake" or len(parts) < 2:
                continue
            target = parts[1]
            if target != package and target not in ALLOWED[package]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not wrong, f"{package} may import only {sorted(ALLOWED[package])}:\n" + "\n".join(wrong)


def test_the_simulation_core_imports_numpy_the_standard_library_and_the_vocabulary_only():
    """...and numba, in its compiled loops' modules only (named ``kernels.py`` or
    ``*_kernels.py``: a room's compiled loops beside the room)."""
    wrong = []
    for path in _sources("server/sim"):
        for name, line in _imports(path):
            top = name.split(".")[0]
            if top == "numba" and path.name.endswith("kernels.py"):
                continue
            if (
                name.startswith("overtake.server.sim")
                or top == "numpy"
                or top in sys.stdlib_module_names
                or name == "__future__"
            ):
                continue
            # The vocabulary, and the errors (plain exception classes, no imports): a
            # configuration mistake is one error type, BadConfig, wherever it is found.
            if any(
                name == module or name.startswith(module + ".")
                for module in ("overtake.protocol.vocabulary", "overtake.protocol.errors")
            ):
                continue
            wrong.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not wrong, (
        "server/sim may import numpy, the standard library, "
        "overtake.protocol.vocabulary and overtake.protocol.errors only (and numba in "
        "*kernels.py):\n" + "\n".join(wrong)
    )


def _loaded_after(statement: str) -> dict:
    """What a fresh interpreter has loaded after ``statement``: top-level module names, and
    which overtake Gymnasium ids are registered if Gymnasium is loaded at all."""
    probe = (
        f"{statement}\n"
        "import json, sys\n"
        "ids = []\n"
        "if 'gymnasium' in sys.modules:\n"
        "    ids = sorted(i for i in sys.modules['gymnasium'].registry "
        "if i.startswith('overtake/'))\n"
        "print(json.dumps({'modules': sorted({m.split('.')[0] for m in sys.modules}), "
        "'ids': ids}))\n"
    )
    return _probe(probe, ROOT)


def _probe(code: str, cwd: Path) -> dict:
    """What ``code``, run in a fresh interpreter in ``cwd``, printed as JSON on its last line."""
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
        cwd=cwd,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_importing_the_simulation_core_loads_numpy_and_the_standard_library_only():
    """...and numba with what it loads (the compiled loops)."""
    baseline = set(_loaded_after("import numpy, numba")["modules"])
    loaded = set(_loaded_after("import overtake.server.sim")["modules"])
    extra = loaded - baseline - set(sys.stdlib_module_names) - {"overtake"}
    assert not extra, f"import overtake.server.sim loaded {sorted(extra)}"
    assert not loaded & set(HEAVY)


def test_no_module_of_the_contract_imports_an_environment_or_a_mechanism():
    """The contract is data: the faces over it (Gymnasium, PettingZoo) live in envs, what
    carries it (Zenoh, the shared memory's futex through ctypes) in ipc."""
    banned = {"gymnasium", "pettingzoo", "zenoh", "ctypes"}
    wrong = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in _sources("protocol")
        for name, line in _imports(path)
        if name.split(".")[0] in banned
    ]
    assert not wrong, "\n".join(wrong)


def test_importing_the_protocol_loads_neither_zenoh_nor_rerun():
    loaded = set(_loaded_after("import overtake.protocol")["modules"])
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))
    # The lazily served codec still works, loads msgpack when used, and nothing else heavy.
    after = set(_loaded_after("import overtake.protocol as p; p.encode")["modules"])
    assert "msgpack" in after
    # (ctypes is not in this set: numpy loads it itself.)
    assert not after & {"zenoh", "gymnasium", "pettingzoo", "rerun", "torch"}


def test_importing_viz_loads_no_rerun():
    assert "rerun" not in _loaded_after("import overtake.viz")["modules"]


def test_environments_are_registered_by_the_client_and_by_nothing_else():
    for statement in (
        "import overtake.server",
        "import overtake.server.sim",
        "import overtake.server.engine.env",
        "import overtake.protocol",
    ):
        assert _loaded_after(statement)["ids"] == [], f"{statement} registered environments"
    ids = [
        "overtake/Highway-v0",
        "overtake/RemoteHighway-v0",
        "overtake/highway-fast-v0",
        "overtake/highway-v0",
    ]
    assert _loaded_after("import overtake.client")["ids"] == ids
    # The entry-point string imports the client first, so it works without an import.
    made = _loaded_after(
        "import gymnasium as gym\ngym.make('overtake.client:overtake/Highway-v0').close()"
    )
    assert made["ids"] == ids


def test_only_the_ray_launcher_imports_ray_and_an_experiment_without_it_loads_none():
    wrong = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for folder in FOLDERS
        for path in _sources(folder)
        for name, line in _imports(path)
        if name.split(".")[0] == "ray" and path != ROOT / "trainers/experiment/ray_launcher.py"
    ]
    assert not wrong, "\n".join(wrong)
    planned_and_launched = (
        "from pathlib import Path\n"
        "from overtake.trainers.experiment import COMMAND, make_plan\n"
        "from overtake.trainers.experiment.launcher import open_launcher\n"
        "plan = make_plan(COMMAND.parse(['ho2018-table8']))\n"
        "with open_launcher(plan.cluster, plan.out, 1.0) as launcher:\n"
        "    assert launcher.running() == 0\n"
    )
    assert "ray" not in _loaded_after(planned_and_launched)["modules"]


def test_every_package_folder_is_listed_in_pyproject():
    """A package left out of pyproject's list works in an editable install and is missing
    from a built one (the Docker images)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    listed = set(project["tool"]["setuptools"]["packages"])
    present = {
        _module_name(init) for folder in FOLDERS for init in (ROOT / folder).rglob("__init__.py")
    }
    assert present == listed, (
        f"missing: {sorted(present - listed)}, stale: {sorted(listed - present)}"
    )


def test_clients_and_trainers_read_the_behaviour_spec_not_the_servers_configuration():
    """What a consumer reads of an arena is the spec's typed fields (protocol 1.5); the full
    configuration (``sim_config``, the spec's ``config_json``) is only recorded."""
    reads = []
    for folder in ("client", "trainers"):
        for path in _sources(folder):
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if "sim_config[" in line or "sim_config.get(" in line:
                    reads.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not reads, "read the behaviour spec instead:\n" + "\n".join(reads)


def _strings(folder: str) -> list[tuple[Path, int, str]]:
    """Every string literal of a folder's sources (docstrings included), with its line."""
    found = []
    for path in _sources(folder):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                found.append((path, node.lineno, node.value))
    return found


def test_faces_and_trainers_ask_for_what_they_read_by_request_not_by_setting_names():
    """envs/ names no simulator setting (a highway-env config is translated beside its scene,
    asked for by name in the open request; the speed's scales come in the spec), and
    trainers/ switch no sensor and set no ego field by their setting names: they ask for
    observations and ego fields by the request's typed fields (protocol 1.10, 1.11)."""
    from overtake.server.sim.config import SimConfig, field_names

    config = SimConfig()
    sections = {name.split(".")[0] for name in field_names(config)}
    dotted = re.compile(r"\b(" + "|".join(sorted(sections)) + r")\.[a-z_]+")
    named = [
        f"{path.relative_to(ROOT)}:{line}: {match.group(0)}"
        for path, line, text in _strings("envs")
        for match in dotted.finditer(text)
    ]
    assert not named, "envs/ names the simulator's settings:\n" + "\n".join(named)
    asked = {f"{name}.enabled" for name in config.sensor_sections()} | {"ego_vector.fields"}
    named = [
        f"{path.relative_to(ROOT)}:{line}: {setting}"
        for path, line, text in _strings("trainers")
        for setting in sorted(asked)
        if setting in text
    ]
    assert not named, (
        "trainers/ ask for observations and ego fields by the open request's fields, not "
        "by setting names:\n" + "\n".join(named)
    )


# client/ by audience (docs/development.md): the sub-packages each may import, besides the
# modules all share (commands: the commands' errors; provenance: the code's commit).
CLIENT_ALLOWED = {
    "wire": set(),
    "policies": set(),
    "envs": {"wire"},
    "episodes": {"wire", "policies"},
    "mlagents": {"wire", "episodes"},
}
CLIENT_SHARED = {"commands", "provenance"}


def test_client_s_sub_packages_import_only_those_below_them():
    found = {p.name for p in (ROOT / "client").iterdir() if (p / "__init__.py").exists()}
    assert found == set(CLIENT_ALLOWED), "a client/ sub-package the layering does not know"
    wrong = []
    for package, allowed in CLIENT_ALLOWED.items():
        for path in sorted((ROOT / "client" / package).glob("*.py")):
            for name, line in _imports(path):
                parts = name.split(".")
                if parts[:2] != ["overtake", "client"] or len(parts) < 3:
                    continue
                if parts[2] not in allowed | CLIENT_SHARED | {package}:
                    wrong.append(f"client/{package}/{path.name}:{line} imports {name}")
    assert not wrong, "\n".join(wrong)


# trainers/ by what its modules are (docs/development.md): the rooms each may import; the
# commands at trainers/' top level may import every room, and overtake-experiment (a command
# of commands: it evaluates and trains) the commands too.
TRAINERS_COMMANDS = {p.stem for p in (ROOT / "trainers").glob("*.py")} - {"__init__"}
TRAINERS_ALLOWED = {
    "learning": set(),
    "config": {"learning"},
    "run": {"learning", "config"},
    "experiment": {"learning", "run", "config"} | TRAINERS_COMMANDS,
}


# server/ by audience (docs/development.md): an engine under a service, the commands at the
# top. The rooms each may import when it runs (a type named for a checker only is not an
# import that runs).
SERVER_ALLOWED = {
    "sim": set(),
    "engine": {"sim"},
    "channels": {"engine", "sim"},
    "service": {"engine", "sim", "channels"},
}


@pytest.mark.parametrize(
    ("package", "rooms"), [("trainers", TRAINERS_ALLOWED), ("server", SERVER_ALLOWED)]
)
def test_a_package_s_rooms_import_only_those_below_them(package: str, rooms: dict) -> None:
    """Each room of ``package`` imports, when it runs, only the rooms (and modules) it may;
    the package keeps at most 12 modules at its top level."""
    folder = ROOT / package
    found = {p.name for p in folder.iterdir() if (p / "__init__.py").exists()}
    assert found == set(rooms), f"a {package}/ room the layering does not know"
    top = sorted(p.stem for p in folder.glob("*.py") if p.stem != "__init__")
    assert len(top) <= 12, f"{package}/ has {len(top)} top-level modules: {top}"
    modules = {_module_name(p) for p in _sources(package)}
    modules |= {m.rsplit(".", 1)[0] for m in modules}
    wrong = []
    for room, allowed in rooms.items():
        for path in sorted((folder / room).rglob("*.py")):
            for name in sorted(_runtime_imports(path, modules)):
                parts = name.split(".")
                if parts[:2] == ["overtake", package] and parts[2] not in allowed | {room}:
                    wrong.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not wrong, "\n".join(wrong)


def _runtime_imports(path: Path, modules: set[str]) -> set[str]:
    """The project's modules ``path`` imports when it runs (local imports included, the
    ``if TYPE_CHECKING:`` ones not; a module's own packages, already loaded, not)."""
    module = _module_name(path)
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    typing_only = {
        id(child)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for child in ast.walk(node)
    }
    names = set()
    for node in ast.walk(tree):
        if id(node) in typing_only or not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        names |= {name for name, line in _imports_of_node(path, node)}
    return {
        name
        for name in names
        if name in modules and name != module and not module.startswith(name + ".")
    }


def _imports_of_node(path: Path, node: ast.Import | ast.ImportFrom) -> list[tuple[str, int]]:
    """What one import statement of ``path`` names (as :func:`_imports` reads it)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    if isinstance(node, ast.Import):
        return [(alias.name, node.lineno) for alias in node.names]
    if node.level:
        base = package.split(".")
        name = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
    else:
        name = node.module or ""
    return [(name, node.lineno)] + [(f"{name}.{alias.name}", node.lineno) for alias in node.names]


def test_no_module_imports_itself_back_not_even_from_inside_a_function():
    """A cycle hidden by an import inside a function still ties two modules into one: each
    is only half a module without the other. The import graph has none."""
    paths = {_module_name(p): p for folder in FOLDERS.values() for p in _sources(folder)}
    graph = {name: _runtime_imports(path, set(paths)) for name, path in paths.items()}
    cycles = []
    for start in graph:
        stack, seen = [(start, [start])], set()
        while stack:
            node, trail = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    cycles.append(trail)
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*trail, nxt]))
    assert not cycles, f"import cycles: {sorted({' -> '.join(sorted(c)) for c in cycles})}"


LIBRARY_FILE_MAX_LINES = 500
HIGHWAY_SIM_MAX_LINES = 250


def test_every_library_file_and_the_simulation_s_class_stay_readable():
    """Every library file within 500 lines (issues 33 and 45); HighwaySim, the class a reader
    of the simulation starts from, within 250 (issue 12)."""
    long = [
        f"{path.relative_to(ROOT)}: {n} lines"
        for folder in FOLDERS
        for path in _sources(folder)
        if (n := len(path.read_text(encoding="utf-8").splitlines())) > LIBRARY_FILE_MAX_LINES
    ]
    assert not long, "\n".join(long)
    core = ROOT / "server" / "sim" / "core.py"
    (sim,) = [
        node
        for node in ast.parse(core.read_text(encoding="utf-8")).body
        if isinstance(node, ast.ClassDef) and node.name == "HighwaySim"
    ]
    assert sim.end_lineno - sim.lineno + 1 <= HIGHWAY_SIM_MAX_LINES
