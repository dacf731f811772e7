"""The package's layering (docs/architecture.md), checked on the real import graph (grimp).

No import circle between modules, and no stage imports a stage above it: optics -> structure ->
kinematics -> io -> models -> runtime, with the edges (dashboard, report, bench, cli) on top.
"""

import grimp
import pytest

#: Stages from the bottom up; a module may import its own stage and those below it.
LAYERS = [
    {"errors", "atomic", "units", "tables", "progress", "cluster", "cnc", "threads"},
    {"optics"},
    {"structure"},
    {"kinematics"},
    {"io"},
    {"models"},
    {"runtime"},
    {"dashboard", "report", "bench"},
    {"cli", "__main__"},
]
#: Upward edges allowed, each with its reason (docs/architecture.md says it too).
ALLOWED_UPWARD = {
    # serve's orchestrator starts the live page; the page never imports the service
    ("fbgcomp.runtime.service", "fbgcomp.dashboard"),
    # ... configured by serve's configuration, whose [dashboard] section is the page's own
    ("fbgcomp.runtime.config", "fbgcomp.dashboard"),
}


@pytest.fixture(scope="session")
def graph():
    return grimp.build_graph("fbgcomp")


def _stage(module: str) -> int:
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    if top == "__init__":
        return 0
    for level, names in enumerate(LAYERS):
        if top in names:
            return level
    raise AssertionError(f"{module}: its package {top!r} is in no layer of docs/architecture.md")


def test_no_import_circle_between_modules(graph):
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if graph.chain_exists(importer=imported, imported=module):
                cycles.append((module, imported))
    assert not cycles, f"import circles: {cycles[:5]}"


def test_no_stage_imports_a_stage_above_it(graph):
    upward = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if _stage(imported) > _stage(module) and not any(
                module.startswith(a) and (imported == b or imported.startswith(b + "."))
                for a, b in ALLOWED_UPWARD
            ):
                upward.append(f"{module} -> {imported}")
    assert not upward, "imports against the data flow:\n" + "\n".join(upward)


def test_every_package_is_placed(graph):
    for module in graph.modules:
        _stage(module)


def test_a_source_file_over_600_lines_says_why_at_its_top():
    """Issue 14: no source file over 600 lines without a reason written at its top."""
    from pathlib import Path

    import fbgcomp

    root = Path(fbgcomp.__file__).parent
    silent = []
    for path in sorted(root.rglob("*.py")):
        lines = path.read_text(encoding="utf-8").splitlines()
        if len(lines) > 600 and not any("600 lines" in line for line in lines[:60]):
            silent.append(f"{path.relative_to(root)} ({len(lines)} lines)")
    assert not silent, "over 600 lines with no reason at the top: " + ", ".join(silent)
