"""Packaging and hygiene of the repository: the wheel carries everything the package reads, the
version is written once, declared test dependencies are checked, no committed file holds a path of
the machine it was made on. (.ci/wheel_smoke.sh installs the wheel in a fresh venv and runs it.)"""

from __future__ import annotations

import importlib.metadata
import json
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement

import environment_support
import relight_torch
from relight_torch.schema import schema_dir

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "relight_torch")
# Absolute paths of a home, temp or work folder; built from parts so that this file does not match.
MACHINE_PATH = "/(" + "|".join(("ho" + "me", "ro" + "ot", "t" + "mp", "wo" + "rk", "Us" + "ers")) + ")/"


def _git(*arguments: str) -> str:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.fail("these checks read the git checkout: run the tests from a clone with git installed")
    return subprocess.run(["git", "-C", str(REPO), *arguments], capture_output=True, text=True, check=False).stdout


def test_no_tracked_file_holds_an_absolute_machine_path():
    hits = _git("grep", "-n", "-I", "-E", MACHINE_PATH).splitlines()
    assert not hits, "absolute machine paths (write them relative to the repository):\n" + "\n".join(hits)


def test_the_path_pattern_finds_what_it_is_for(tmp_path):
    # The guard above passes on an empty grep: check that the pattern matches each kind of path.
    for path in ("/" + "home/a/x", "/" + "tmp/q/bench", "/" + "work/shared/assets", "/" + "Users/b/y"):
        assert re.search(MACHINE_PATH, f"see `{path}`"), path
    assert not re.search(MACHINE_PATH, "docs/bench/cornell_64x48 and ./textures/a.png")


@pytest.mark.slow
def test_the_wheel_holds_every_tracked_file_of_the_packages(tmp_path):
    # Built from a copy of the tracked files (as a clean clone), without build isolation (no index):
    # with the test extra's setuptools.
    source = tmp_path / "source"
    for name in _git("ls-files").splitlines():
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
    command = [
        sys.executable,
        "-m",
        "pip",
        "wheel",
        "--quiet",
        "--no-deps",
        "--no-build-isolation",
        "--wheel-dir",
        str(tmp_path / "dist"),
        str(source),
    ]
    subprocess.run(command, check=True, capture_output=True, text=True)
    (wheel,) = (tmp_path / "dist").glob("relight-*.whl")
    packaged = set(zipfile.ZipFile(wheel).namelist())
    tracked = {name for name in _git("ls-files", *PACKAGES).splitlines() if not name.endswith(".gitignore")}
    assert tracked, "no tracked files found under " + ", ".join(PACKAGES)
    assert not tracked - packaged, f"tracked but not in the wheel (package-data?): {sorted(tracked - packaged)}"
    version = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert wheel.name.startswith(f"relight-{version}-")


def test_schema_plugin_is_found_as_package_data():
    folder = schema_dir()
    assert folder == Path(relight_torch.__file__).parent / "schemas"
    assert {"plugInfo.json", "generatedSchema.usda", "schema.usda"} <= {p.name for p in folder.iterdir()}


def test_the_version_is_written_once():
    version = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert relight_torch.__version__ == importlib.metadata.version("relight") == version
    literal = re.escape(version)
    hits = _git("grep", "-n", "-E", rf"__version__ *= *['\"][0-9]+\.|['\"]{literal}['\"]", "--", "*.py").splitlines()
    assert not hits, "version written outside pyproject.toml:\n" + "\n".join(hits)


def test_relight_version_prints_the_installed_version():
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip() == f"relight {relight_torch.__version__}"


def _pyproject(tmp_path: Path, dependencies: list[str], extras: dict[str, list[str]]) -> Path:
    # JSON arrays of strings are TOML arrays.
    lines = [
        "[project]",
        'name = "relight"',
        f"dependencies = {json.dumps(dependencies)}",
        "[project.optional-dependencies]",
        *(f"{name} = {json.dumps(values)}" for name, values in extras.items()),
    ]
    path = tmp_path / "pyproject.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_declared_test_requirements_expand_the_projects_own_extras(tmp_path):
    pyproject = _pyproject(
        tmp_path,
        ["numpy==2.4.6"],
        {
            "distributed": ["dask==2026.8.0"],
            "lint": ["ruff==0.17.5"],
            "test": ["relight[distributed]", "pytest==9.2.0", 'mitsuba==3.9.1; sys_platform == "nowhere"'],
        },
    )
    names = [r.name for r in environment_support.declared_test_requirements(pyproject)]
    assert names == ["numpy", "pytest", "dask"]


def test_the_projects_declarations_include_the_optional_ones():
    names = {r.name for r in environment_support.declared_test_requirements()}
    assert {"mitsuba", "dask", "distributed", "pytest-xdist", "usd-core"} <= names


def test_a_missing_wrong_or_unimportable_dependency_is_a_problem(monkeypatch):
    problem = environment_support.requirement_problem
    assert problem(Requirement("pytest==" + importlib.metadata.version("pytest"))) is None
    assert "not installed" in problem(Requirement("no-such-distribution-relight==1.0"))
    assert "but " + importlib.metadata.version("pytest") + " is installed" in problem(Requirement("pytest==0.1"))
    monkeypatch.setattr(environment_support, "import_name", lambda distribution: "no_such_module_relight")
    message = problem(Requirement("pytest"))
    assert "import no_such_module_relight failed: ModuleNotFoundError" in message and "\n" not in message


def test_import_names_come_from_the_installed_files():
    names = {
        d: environment_support.import_name(d) for d in ("usd-core", "openexr", "pytest-xdist", "materialx", "torch")
    }
    assert names == {
        "usd-core": "pxr",
        "openexr": "OpenEXR",
        "pytest-xdist": "xdist",
        "materialx": "MaterialX",
        "torch": "torch",
    }


def test_a_broken_declared_dependency_stops_the_run(tmp_path):
    # End to end: pytest itself refuses to start (usage error, exit 4) and names the package.
    tests = tmp_path / "tests"
    tests.mkdir()
    shutil.copy2(REPO / "tests" / "environment_support.py", tests)
    shutil.copy2(REPO / "tests" / "conftest.py", tests)
    _pyproject(tmp_path, [], {"test": ["pytest==0.1"]})
    (tests / "test_nothing.py").write_text("def test_nothing():\n    pass\n")
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", str(tests)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == pytest.ExitCode.USAGE_ERROR, result.stdout + result.stderr
    assert "pytest==0.1 is declared in pyproject.toml but" in result.stderr


def test_bench_context_names_no_path_of_the_machine(tmp_path):
    # bench.json is committed under docs/bench/: its context once held the absolute output folder.
    from pipeline.benchmarks.bench.runner import BenchConfig, context

    written = json.dumps(context(BenchConfig(out=tmp_path / "bench", quick=True)))
    assert str(tmp_path) not in written and '"quick": true' in written
