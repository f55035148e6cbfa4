"""The two layering rules of docs/architecture.md a change is likeliest to break, read from the
source with `ast` (nothing is imported): no method imports another method's module, and the
benchmark never imports the reference methods (but for the `reproduce` command)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def imported_modules(path: Path, package: str) -> set[str]:
    """Every module `path` imports, absolute (relative imports resolved against `package`)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import module`
    return out


METHOD_FILES = sorted(p for p in (ROOT / "reference" / "methods").glob("*.py") if p.name != "__init__.py")


@pytest.mark.parametrize("path", METHOD_FILES, ids=lambda p: p.stem)
def test_no_method_imports_another_method(path):
    others = {f"reference.methods.{p.stem}" for p in METHOD_FILES if p != path}
    hits = imported_modules(path, "reference.methods") & others
    assert not hits, f"{path.name} imports {sorted(hits)}: share the part through reference/common instead"


def test_the_benchmark_never_imports_the_reference_methods():
    """... except the `reproduce` command, which loads them when it runs (its one lazy import)."""
    bad = []
    for path in sorted((ROOT / "skyeyes_bench").rglob("*.py")):
        pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
        if any(m == "reference" or m.startswith("reference.") for m in imported_modules(path, pkg)):
            bad.append(str(path.relative_to(ROOT)))
    assert bad == ["skyeyes_bench/commands/reproduce.py"]


def test_the_reader_sees_imports_of_every_spelling(tmp_path):
    """The check itself can fail: each spelling of an import of another method is found."""
    for line in ("import reference.methods.sugar", "from reference.methods import sugar",
                 "from reference.methods.sugar import SuGaR", "from . import sugar", "from .sugar import SuGaR"):
        f = tmp_path / "toy.py"
        f.write_text(line + "\n")
        assert "reference.methods.sugar" in imported_modules(f, "reference.methods"), line
