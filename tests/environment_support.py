"""What the test run needs from its environment (used by conftest.py, tested in test_packaging.py).

- Every dependency pyproject.toml declares for the tests (the package's own, the `test` extra and
  the project's extras it names) must be installed at its pinned version and import: a broken
  install is an error of the run, never a skipped test.
- torch.compile's C++ backend (inductor) needs a C++ compiler: `find_cxx_compiler` finds it the way
  inductor does, so that a test skips exactly where compiling could not work.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import shutil
import subprocess
import tomllib
from pathlib import Path

from packaging.requirements import Requirement

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
TEST_EXTRA = "test"


def declared_test_requirements(pyproject: Path = PYPROJECT) -> list[Requirement]:
    """The project's dependencies and its `test` extra, with the project's own extras that it names
    (`relight[distributed]`) expanded in their place; requirements whose marker is false dropped."""
    project = tomllib.loads(pyproject.read_text())["project"]
    extras = project.get("optional-dependencies", {})
    requirements, pending, seen = [], [*project["dependencies"], *extras[TEST_EXTRA]], set()
    while pending:
        requirement = Requirement(pending.pop(0))
        if requirement.marker is not None and not requirement.marker.evaluate({"extra": TEST_EXTRA}):
            continue
        if requirement.name == project["name"]:
            pending += [line for extra in sorted(requirement.extras - seen) for line in extras[extra]]
            seen |= requirement.extras
        else:
            requirements.append(requirement)
    return requirements


def import_name(distribution: str) -> str:
    """The top-level module an installed distribution provides (usd-core -> pxr, openexr -> OpenEXR),
    read from its installed files: the one named like the distribution, else the first; the project
    name with '_' for '-' when it lists none."""
    files = importlib.metadata.distribution(distribution).files or []
    tops = {path.parts[0] for path in files if len(path.parts) > 1 or path.suffix in (".py", ".so", ".pyd")}
    modules = sorted(
        {top.split(".")[0] for top in tops if not top.endswith((".dist-info", ".libs", ".data"))}, key=str.lower
    )
    modules = [module for module in modules if module.isidentifier() and not module.startswith("_")]
    named = [module for module in modules if _normalized(module) == _normalized(distribution)]
    return (named or modules or [distribution.replace("-", "_")])[0]


def _normalized(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


def requirement_problem(requirement: Requirement) -> str | None:
    """Why `requirement` is unusable here (not installed, another version, fails to import), or None."""
    try:
        installed = importlib.metadata.version(requirement.name)
    except importlib.metadata.PackageNotFoundError:
        return f"{requirement} is declared in pyproject.toml but not installed"
    if not requirement.specifier.contains(installed, prereleases=True):
        return f"{requirement} is declared in pyproject.toml but {installed} is installed"
    module = import_name(requirement.name)
    try:
        importlib.import_module(module)
    except Exception as error:  # any failure to import is the broken install this check is for
        return f"{requirement}: import {module} failed: {type(error).__name__}: {error}".splitlines()[0]
    return None


def find_cxx_compiler() -> str | None:
    """The C++ compiler inductor would run ($CXX, else g++), or None when it finds none."""
    # inductor's own search (private, torch is pinned): a test then skips exactly where it would fail.
    from torch._inductor import cpp_builder, exc

    try:
        return str(cpp_builder.get_cpp_compiler())
    except exc.InvalidCxxCompiler:
        return None


def describe_cxx_compiler() -> str:
    """One line for the test report's header: the compiler's path and version, or that there is none."""
    compiler = find_cxx_compiler()
    if compiler is None:
        return "C++ compiler for torch.compile: none found (tests that need one skip)"
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout.partition("\n")[0]
    return f"C++ compiler for torch.compile: {shutil.which(compiler) or compiler} ({version})"
