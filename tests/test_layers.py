"""The layers stay one-way: checked on the import statements of every module (AST, any depth)."""

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imports(path: Path, top_level_only: bool = False) -> set[str]:
    """Every module name `path` imports (relative imports resolved against its package)."""
    tree = ast.parse(path.read_text())
    pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1]) if path.is_relative_to(ROOT) else ""
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


# The modules of coin_cl that diffusion/ may import: leaves that import nothing of coin_cl (so the 2D
# branch never reaches the engine or the pipeline through them); coin_cl.checkpoint imports torch.
DIFFUSION_MAY_IMPORT = ("coin_cl.atomic", "coin_cl.checkpoint", "coin_cl.crop", "coin_cl.timing")


def test_diffusion_imports_only_coin_cl_leaves():
    for f in modules("diffusion"):
        outside = {n for n in hits(imports(f), "coin_cl") if not hits({n}, "coin_cl.diffusion")}
        bad = {n for n in outside if not any(hits({n}, leaf) for leaf in DIFFUSION_MAY_IMPORT)}
        assert not bad, f"{f} imports {bad}; diffusion/ may import only {DIFFUSION_MAY_IMPORT}"
    for leaf in DIFFUSION_MAY_IMPORT:
        path = ROOT / (leaf.replace(".", "/") + ".py")
        assert not hits(imports(path), "coin_cl"), f"{path} must import nothing of coin_cl"


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


def public_names(package_init: Path) -> set[str]:
    """The names in a package's `__all__` (read from its __init__.py's AST, nothing imported)."""
    for node in ast.parse(package_init.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            return {ast.literal_eval(e) for e in node.value.elts}
    raise AssertionError(f"{package_init} has no __all__")


def private_engine_imports(path: Path, public: set[str]) -> set[str]:
    """The engine modules and names `path` imports that are not `coin_cl.engine.<public name>`."""
    engine = hits(imports(path), "coin_cl.engine") - {"coin_cl.engine"}
    return {n for n in engine if n.removeprefix("coin_cl.engine.") not in public}


def test_stages_use_only_the_engines_public_names():
    public = public_names(ROOT / "coin_cl/engine/__init__.py")
    assert {"warp_features", "support_mask", "rasterize"} <= public
    stages = modules("coin_cl/pipeline")
    assert len(stages) >= 8
    for f in stages:
        private = private_engine_imports(f, public)
        assert not private, f"{f} reaches into the engine: {private}; import public names of coin_cl.engine"


def test_public_names_rule_catches_a_private_import(tmp_path):
    """The rule above can fail: reaching into engine.ops or engine.constants is caught, at any depth."""
    probe = tmp_path / "probe.py"
    probe.write_text("from coin_cl.engine import warp_features\n"
                     "def f():\n    from coin_cl.engine.ops.warp import support_mask\n"
                     "import coin_cl.engine.constants\n")  # fmt: skip
    public = public_names(ROOT / "coin_cl/engine/__init__.py")
    assert private_engine_imports(probe, public) == {
        "coin_cl.engine.ops.warp", "coin_cl.engine.ops.warp.support_mask", "coin_cl.engine.constants"
    }  # fmt: skip


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_edges(path: Path, known: set[str]) -> set[str]:
    """The modules of `known` that `path` imports, at any depth (functions, TYPE_CHECKING blocks
    included): `from a.b import c` is an edge to the module a.b.c where that is a module, else to
    a.b; a name is taken at its longest prefix that is a module."""
    tree = ast.parse(path.read_text())
    pkg = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join([*parts, base]) if base else ".".join(parts)
            subs = {f"{base}.{a.name}" for a in node.names}
            names |= {n for n in subs if n in known} or {base}
            if any(n not in known for n in subs):
                names.add(base)
    out = set()
    for n in names:
        parts = n.split(".")
        hit = next(
            (".".join(parts[:i]) for i in range(len(parts), 0, -1) if ".".join(parts[:i]) in known), None
        )
        if hit is not None:
            out.add(hit)
    return out - {module_name(path)}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in graph:
                    continue
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def import_graph(folders: tuple[str, ...] = ("coin_cl", "diffusion")) -> dict[str, set[str]]:
    files = {module_name(f): f for folder in folders for f in modules(folder)}
    known = set(files)
    return {m: import_edges(f, known) for m, f in files.items()}


def test_no_import_cycles():
    """No module reaches itself through imports (type-only and function-level ones count: a cycle
    is a cycle for a reader even where Python would tolerate it)."""
    graph = import_graph()
    assert len(graph) > 100 and "coin_cl.pipeline.coin" in graph
    assert "coin_cl.pipeline.config" in graph["coin_cl.pipeline.stages"]  # a TYPE_CHECKING import
    assert cycles(graph) == []


def test_cycle_rule_finds_a_planted_cycle(tmp_path, monkeypatch):
    """The checker can fail: on a fake graph, and on a fake package with a lazy + a TYPE_CHECKING edge."""
    fake = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e", "d"}, "f": {"g"}, "g": {"f"}}
    assert cycles(fake) == [["a", "b", "c"], ["f", "g"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "top.py").write_text("from fakepkg import config\ndef f():\n    from fakepkg.low import g\n")
    (pkg / "low.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                "    from fakepkg.top import f\n")  # fmt: skip
    (pkg / "config.py").write_text("from . import low\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    graph = import_graph(("fakepkg",))
    assert graph["fakepkg.top"] == {"fakepkg.config", "fakepkg.low"}
    assert cycles(graph) == [["fakepkg.config", "fakepkg.low", "fakepkg.top"]]


def test_scaffold_imports_nothing_of_carving():
    """The generic Scaffold-GS model knows a volume to keep empty, not the experimental carve that
    makes one (the pipeline sets it; `model_kinds` restores it from a checkpoint)."""
    assert not hits(imports(ROOT / "coin_cl/gs/scaffold.py"), "coin_cl.gs.carve")
