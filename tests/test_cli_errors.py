"""`relight` never shows a user a traceback: bad input is one line and exit status 2; an unexpected
error is one line naming the subcommand and a log file that holds the traceback (exit status 1),
or the traceback itself with --debug."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.commands import info
from pipeline.scenes import SCENES


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize(
    "argv",
    [
        ["bake", "{missing}", "--camera", "/Cam", "--out", "{tmp}/out"],
        ["render", "{missing}", "-o", "{tmp}/out.exr"],
        ["render", "{file}", "-o", "{tmp}/out.exr"],
        ["info", "{missing}"],
        ["reference", "{missing}", "--camera", "/Cam", "-o", "{tmp}/out.exr"],
    ],
)
def test_bad_input_is_one_line_and_status_2(tmp_path, capsys, argv):
    (tmp_path / "file.usda").write_text("not usd")
    paths = {"missing": str(tmp_path / "missing.usda"), "file": str(tmp_path / "file.usda"), "tmp": str(tmp_path)}
    assert cli.main([arg.format(**paths) for arg in argv]) == 2
    assert _one_line(capsys.readouterr().err).startswith("relight: error: ")


def test_an_output_folder_that_is_a_file_is_bad_input(tmp_path, capsys):
    shot = SCENES["cornell_box"].write(tmp_path)
    blocker = tmp_path / "blocker"
    blocker.write_text("")
    status = cli.main(
        [
            "bake",
            str(shot),
            "--camera",
            SCENES["cornell_box"].camera,
            "--width",
            "8",
            "--height",
            "8",
            "--out",
            str(blocker),
        ]
    )
    assert status == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("relight: error: ") and str(blocker) in line


def _break_info(monkeypatch):
    def run(args):
        raise ZeroDivisionError("a bug deep inside")

    monkeypatch.setattr(info, "run", run)


def test_internal_error_names_the_step_and_a_log(tmp_path, capsys, monkeypatch):
    _break_info(monkeypatch)
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(cli.tempfile, "tempdir", None)  # read TMPDIR again
    assert cli.main(["info", str(tmp_path / "any.usda")]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("relight: internal error in 'info': ZeroDivisionError: a bug deep inside")
    log = Path(re.search(r"traceback in (\S+);", line).group(1))
    assert log.parent == tmp_path / "relight-logs"
    text = log.read_text()
    assert text.startswith("relight info ")
    assert "Traceback (most recent call last)" in text and "ZeroDivisionError: a bug deep inside" in text


def test_debug_prints_the_traceback(tmp_path, capsys, monkeypatch):
    _break_info(monkeypatch)
    assert cli.main(["--debug", "info", str(tmp_path / "any.usda")]) == 1
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "ZeroDivisionError: a bug deep inside" in err
    assert err.strip().splitlines()[-1] == "relight: internal error in 'info': ZeroDivisionError: a bug deep inside"
