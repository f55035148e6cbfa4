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


# --------------------------------------------------------------------------- sizes and ids

#: What the size rules cover (tests excepted): the two packages, bench/ and scripts/.
LIBRARY = ("skyeyes_bench", "reference", "bench", "scripts")
MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80


def library_files() -> list[Path]:
    return sorted(p for d in LIBRARY for p in (ROOT / d).rglob("*.py") if "__pycache__" not in p.parts)


def oversized(path: Path) -> list[str]:
    """What in `path` breaks the size rules: the file over MAX_FILE_LINES lines, each function
    (or method) over MAX_FUNCTION_LINES lines from its `def` to its last line."""
    text = path.read_text()
    out = []
    if (n := len(text.splitlines())) > MAX_FILE_LINES:
        out.append(f"{path.name}: {n} lines (at most {MAX_FILE_LINES}: split it by concept)")
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if (n := node.end_lineno - node.lineno + 1) > MAX_FUNCTION_LINES:
                out.append(f"{path.name}:{node.lineno} {node.name}: {n} lines (at most {MAX_FUNCTION_LINES})")
    return out


def test_no_library_file_or_function_is_over_the_limits():
    bad = [msg for p in library_files() for msg in oversized(p)]
    assert not bad, "\n".join(bad)


def test_the_size_check_fails_on_a_planted_long_function_and_file(tmp_path):
    f = tmp_path / "planted.py"
    f.write_text("def short():\n    return 1\n\n\nclass A:\n    def long(self):\n" + "        x = 1\n" * 80)
    assert oversized(f) == [f"planted.py:6 long: {MAX_FUNCTION_LINES + 1} lines (at most {MAX_FUNCTION_LINES})"]
    f.write_text("x = 1\n" * (MAX_FILE_LINES + 1))
    assert oversized(f) == [f"planted.py: {MAX_FILE_LINES + 1} lines (at most {MAX_FILE_LINES}: split it by concept)"]
    f.write_text("def ok():\n" + "    x = 1\n" * (MAX_FUNCTION_LINES - 1))
    assert oversized(f) == []


def method_ids() -> set[str]:
    """The registry's ids, read from reference/registry.py's source."""
    tree = ast.parse((ROOT / "reference" / "registry.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "METHODS":
            return {k.value for k in node.value.keys}
    raise AssertionError("reference/registry.py has no METHODS table")


def named_ids(path: Path, ids: set[str]) -> set[str]:
    """The method ids `path` names: string constants equal to one, and any lookup in the registry
    (`get_method_class`, whatever it is given)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in ids:
            out.add(node.value)
        if isinstance(node, ast.Name) and node.id == "get_method_class":
            out.add("get_method_class")
        if isinstance(node, ast.alias) and node.name == "get_method_class":
            out.add("get_method_class")
    return out


#: A method's string equal to another id that names no method, and why.
NOT_A_METHOD = {("nerf", "mvs"): "nerf's `init` value: its start is the fused MVS cloud (common/mvs_start), not the row"}


@pytest.mark.parametrize("path", METHOD_FILES, ids=lambda p: p.stem)
def test_no_method_names_another_method(path):
    """A method shares a part of reference/common (`common.sugar`, `common.mvs_cloud`,
    `common.priors.PRIOR_PARTS`), never another method by its id. A method's file names its own
    id(s) only: the ids of the registry entries that point at it."""
    ids = method_ids()
    own = {k for k, v in __import__("reference.registry", fromlist=["METHODS"]).METHODS.items()
           if v.split(":")[0] == f"reference.methods.{path.stem}"}
    hits = {h for h in named_ids(path, ids) - own if (path.stem, h) not in NOT_A_METHOD}
    assert not hits, f"{path.name} names {sorted(hits)}: use the part they are made of (reference/common)"


def test_no_part_looks_a_method_up():
    """reference/common never looks a method up in the registry (what it uses is a part)."""
    bad = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "reference" / "common").rglob("*.py")
                 if "get_method_class" in named_ids(p, set()))
    assert not bad


def test_the_id_check_sees_a_planted_id_and_lookup(tmp_path):
    f = tmp_path / "toy.py"
    f.write_text('PRIOR = "sugar"\n')
    assert named_ids(f, {"sugar", "mvs"}) == {"sugar"}
    f.write_text("from reference.registry import get_method_class\nm = get_method_class(name)\n")
    assert named_ids(f, {"sugar"}) == {"get_method_class"}
    f.write_text('"""The `sugar` row."""\nx = "sugary"\n')  # a docstring mentioning it is prose; not a constant equal to an id
    assert named_ids(f, {"sugar"}) == set()
