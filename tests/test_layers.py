"""The layers stay one-way: checked on the import statements of every module (AST, any depth)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imports(path: Path, top_level_only: bool = False) -> set[str]:
    """Every module name `path` imports (relative imports resolved against its package)."""
    tree = ast.parse(path.read_text())
    pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    nodes = tree.body if top_level_only else ast.walk(tree)
    out: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join([*parts, base]) if base else ".".join(parts)
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return out


def modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def hits(names: set[str], prefix: str) -> set[str]:
    return {n for n in names if n == prefix or n.startswith(prefix + ".")}


def test_fast_path_never_imports_the_twins():
    engine = [
        f for f in (ROOT / "coin_cl/engine").glob("*.py")
        if not f.name.startswith("reference") and f.name != "rendering.py"
    ]  # fmt: skip
    fast = [*modules("coin_cl/engine/ops"), *engine]
    assert len(fast) >= 12
    for f in fast:
        assert not [n for n in imports(f) if n.startswith("coin_cl.engine.reference")], f
    # rendering.py loads the twins only when backend="torch" is asked for, inside a function.
    assert not hits(
        imports(ROOT / "coin_cl/engine/rendering.py", top_level_only=True), "coin_cl.engine.reference"
    )


def test_engine_imports_nothing_above_it():
    for f in modules("coin_cl/engine"):
        above = {n for n in imports(f) if n.startswith("coin_cl.") and not n.startswith("coin_cl.engine")}
        assert not above, f"{f} imports {above}"


def test_diffusion_never_imports_opencl():
    files = modules("diffusion")
    assert files
    for f in files:
        names = imports(f)
        assert not hits(names, "pyopencl") and not hits(names, "coin_cl.engine"), f


def test_only_the_cli_imports_the_cli():
    cli = ROOT / "coin_cl/cli"
    assert (cli / "__init__.py").is_file()
    for f in [*modules("coin_cl"), *modules("diffusion"), *modules("benchmarks")]:
        if f.is_relative_to(cli):
            continue
        assert not hits(imports(f), "coin_cl.cli"), f


def test_testing_kit_is_for_tests_only():
    for f in modules("coin_cl"):
        if f.name == "testing.py":
            continue
        assert not hits(imports(f), "coin_cl.testing"), f
