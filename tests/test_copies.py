"""One file per algorithm, CleanRL's shape: every line of the algorithm in its script, the plumbing imported from
rl_utils (as CleanRL imports cleanrl_utils), each script a copy of its base that changes only what its method changes.
These tests keep that shape and the repository formatted."""

import ast
import importlib.util
import os
import pkgutil
import re
import subprocess
import sys

import pytest

import rl_utils
from conftest import REPO, SCRIPTS, base_of

MAX_LINE = 127  # ruff.toml's line length, which the formatter does not enforce on strings and comments


def tree(script: str) -> ast.Module:
    return ast.parse(open(os.path.join(REPO, f"{script}_continuous_action.py")).read())


def defined(module_tree: ast.Module) -> list:
    """The names a module defines at top level (classes, functions, assignments), in file order."""
    names = []
    for node in module_tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            names += [t.id for t in node.targets if isinstance(t, ast.Name)]
    return names


def machinery() -> set:
    """Every name rl_utils' modules define."""
    names = set()
    for info in pkgutil.iter_modules(rl_utils.__path__):
        path = os.path.join(REPO, "rl_utils", f"{info.name}.py")
        names |= set(defined(ast.parse(open(path).read())))
    return names


def test_every_script_with_a_base_names_it_and_the_roots_are_cleanrls():
    roots = [script for script in SCRIPTS if base_of(script) is None]
    assert set(roots) <= {"td3", "ppo"}, (
        f"{roots}: a script copied from another names it in its header, as `diff td3_continuous_action.py "
        "ddpg_continuous_action.py` (docs/forking.md)"
    )
    assert all(base_of(script) in SCRIPTS for script in SCRIPTS if base_of(script)), "a header names a missing base"


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_script_copies_no_machinery(script):
    """The plumbing lives once, in rl_utils: a script that defines one of its names has copied it."""
    copied = set(defined(tree(script))) & machinery()
    assert not copied, f"{script} defines {sorted(copied)}, which rl_utils has: import it from there"


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_script_reads_as_cleanrls(script):
    """Imports, Args, the networks and the algorithm's functions, main, and a one-line __main__."""
    body = tree(script).body
    names = defined(tree(script))
    assert names[0] == "Args", f"{script}: Args comes first after the imports"
    assert names[-1] == "main", f"{script}: main comes last, after everything it uses"
    last = body[-1]
    is_main = isinstance(last, ast.If) and ast.unparse(last.test) == "__name__ == '__main__'"
    assert is_main and len(last.body) == 1, f"{script}: ends with a one-line `if __name__ == '__main__':`"
    first_code = next(i for i, node in enumerate(body) if not isinstance(node, (ast.Import, ast.ImportFrom, ast.Expr)))
    assert all(isinstance(node, (ast.Import, ast.ImportFrom)) for node in body[:first_code] if not isinstance(node, ast.Expr))


def test_lines_fit_the_formatters_length():
    paths = [os.path.join(REPO, f"{script}_continuous_action.py") for script in SCRIPTS]
    paths += [
        os.path.join(REPO, "rl_utils", name) for name in os.listdir(os.path.join(REPO, "rl_utils")) if name.endswith(".py")
    ]
    long = [
        f"{os.path.relpath(path, REPO)}:{number}"
        for path in paths
        for number, line in enumerate(open(path).read().splitlines(), 1)
        if len(line) > MAX_LINE
    ]
    assert not long, f"lines over {MAX_LINE} characters: {long}"


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed (it is in requirements.txt)")
def test_repository_is_formatted_with_ruff():
    result = subprocess.run([sys.executable, "-m", "ruff", "format", "--check", "."], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, f"run `ruff format .`:\n{result.stdout}{result.stderr}"


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed (it is in requirements.txt)")
def test_repository_passes_ruffs_lint():
    """ruff.toml's rules: no unused import or variable, no undefined name (a typo in a branch no test runs)."""
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=REPO, capture_output=True, text=True
    )
    assert result.returncode == 0, f"run `ruff check --fix .`, then fix what remains by hand:\n{result.stdout}{result.stderr}"


def test_rl_utils_modules_import_each_other_without_a_cycle_and_name_no_commits():
    """Each rl_utils module has one job and imports only the modules below it: no cycle (a module that needs one
    above it has taken another's job). No code or message names a commit hash: a commit says nothing to a user."""
    imports = {}
    for info in pkgutil.iter_modules(rl_utils.__path__):
        source = open(os.path.join(REPO, "rl_utils", f"{info.name}.py")).read()
        found = set()
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rl_utils"):
                found |= {node.module.split(".")[1]} if "." in node.module else {alias.name for alias in node.names}
            elif isinstance(node, ast.Import):
                found |= {alias.name.split(".")[1] for alias in node.names if alias.name.startswith("rl_utils.")}
        imports[info.name] = found - {info.name}
        assert not re.search(r"\b[0-9a-f]{7,40}\b", source), f"rl_utils/{info.name}.py names a commit"

    def visit(module, path):
        assert module not in path, f"rl_utils imports in a cycle: {' -> '.join([*path, module])}"
        for imported in imports.get(module, ()):
            visit(imported, [*path, module])

    for module in imports:
        visit(module, [])
    assert imports["errors"] == set() and "run" not in set().union(*imports.values())
