"""One command line (issue 14): --version, choices in any case, --out, --eop, help texts."""

from __future__ import annotations

import importlib.metadata
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from pipeline.cli import app
from seqat.errors import InputDataError

REACHED = "reached the stage"


class Reached(InputDataError):
    """Raised by a fake stage: the options were parsed and validated."""


def test_version() -> None:
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0, result.output
    assert result.stdout == f"seqat {importlib.metadata.version('seqat')}\n"


def fake_stage(calls: list[dict[str, object]]):  # type: ignore[no-untyped-def]
    def stage(*args: object, **kwargs: object) -> None:
        calls.append({"args": args, **kwargs})
        raise Reached(REACHED)

    return stage


def _patch_stages(monkeypatch: pytest.MonkeyPatch, calls: list[dict[str, object]]) -> None:
    import pipeline.cli.process as process_cli
    from pipeline.ortho import stage as ortho_stage
    from pipeline.reference import sfm_stage
    from pipeline.reference import stage as reference_stage
    from pipeline.run import runner, watch

    fake = fake_stage(calls)
    monkeypatch.setattr(runner, "run_flight", fake)
    monkeypatch.setattr(watch, "watch_flight", fake)
    monkeypatch.setattr(process_cli, "adjust_flight", fake)
    monkeypatch.setattr(ortho_stage, "flight_lidar", lambda flight: None)
    monkeypatch.setattr(ortho_stage, "orthorectify_run", fake)
    monkeypatch.setattr(reference_stage, "run_reference", fake)
    monkeypatch.setattr(sfm_stage, "run_sfm_check", fake)
    faults = types.ModuleType("pipeline.bench.faults.suite")
    faults.run_fault_bench = fake  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pipeline.bench.faults.suite", faults)


def _value(call: dict[str, object], key: str) -> str:
    if key == "method":
        return str(getattr(call["method"], "value", call["method"]))
    if key == "prior":
        return str(call["args"][1].prior.value)  # type: ignore[index]
    if key == "robust_loss":
        loss = call["args"][1].robust_loss  # type: ignore[index]
        return "run" if loss is None else str(loss.value)
    if key == "matching":
        return str(call["args"][1].matching.value)  # type: ignore[index]
    if key == "eop":
        return str(call["eop_source"])
    if key == "case":
        return ",".join(call["cases"])  # type: ignore[arg-type]
    raise AssertionError(key)


#: Every choice option of every command: (argv before the option, option, a value in another
#: case, the value it means, what the stage receives, the choices the error lists).
CHOICES = [
    (["run", "F", "--out", "O"], "--method", "SEQ-R", "seq-r", "method", "seq-r, seq-f, sim"),
    (["watch", "F", "--out", "O"], "--method", "Sim", "sim", "method", "seq-r, seq-f, sim"),
    (["process", "F", "--out", "O", "--no-ortho"], "--method", "Seq-F", "seq-f", "method",
     "seq-r, seq-f, sim"),
    (["reference", "O"], "--prior", "POSITION", "position", "prior", "pose, position"),
    (["reference", "O"], "--robust-loss", "Huber", "huber", "robust_loss",
     "run, trivial, huber, cauchy, soft_l1"),
    (["reference", "O"], "--robust-loss", "RUN", "run", "robust_loss",
     "run, trivial, huber, cauchy, soft_l1"),
    (["reference", "O", "--sfm"], "--matching", "Sequential", "sequential", "matching",
     "spatial, sequential, exhaustive"),
    (["ortho", "O"], "--eop", "Reference", "reference", "eop",
     "run, reference, seq-r, seq-f, sim"),
    (["ortho", "O"], "--eop", "RUN", "run", "eop", "run, reference, seq-r, seq-f, sim"),
]


@pytest.mark.parametrize(("argv", "option", "given", "meant", "key", "listed"), CHOICES)
def test_choices_in_any_case(argv: list[str], option: str, given: str, meant: str, key: str,
                             listed: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                             ) -> None:
    calls: list[dict[str, object]] = []
    _patch_stages(monkeypatch, calls)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, [*argv, option, given])
    assert result.stderr == f"seqat: error: {REACHED}\n", result.output
    assert result.exit_code == 2
    assert _value(calls[0], key) == meant


@pytest.mark.parametrize(("argv", "option", "given", "meant", "key", "listed"), CHOICES)
def test_a_wrong_choice_lists_the_choices(argv: list[str], option: str, given: str, meant: str,
                                          key: str, listed: str, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[dict[str, object]] = []
    _patch_stages(monkeypatch, calls)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, [*argv, option, "Nope"])
    assert result.exit_code == 2
    assert result.stderr == f"seqat: error: {option}: expected one of {listed}, got 'Nope'\n"
    assert calls == []


def test_bench_faults_case_in_any_case(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[dict[str, object]] = []
    _patch_stages(monkeypatch, calls)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["bench", "faults", "--out", "b", "--case", "Strip",
                                      "--case", "BLOCK"])
    assert result.stderr == f"seqat: error: {REACHED}\n", result.output
    assert _value(calls[0], "case") == "strip,block"


def test_bench_module_choices_in_any_case() -> None:
    from pipeline.bench.fuzz.suite import parse_args

    assert parse_args(["--flight", "Seneca_Mini"]).flight == ["seneca_mini"]


# ------------------------------------------------------------------ --out and seqat feed


def test_feed_takes_out(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.run import feed

    calls: list[dict[str, object]] = []
    monkeypatch.setattr(feed, "feed_flight", fake_stage(calls))
    cli = CliRunner()
    result = cli.invoke(app, ["feed", "SRC", "--out", str(tmp_path / "d")])
    assert result.stderr == f"seqat: error: {REACHED}\n"
    assert calls[-1]["args"] == (Path("SRC"), tmp_path / "d")
    # the old form still works, with a note
    result = cli.invoke(app, ["feed", "SRC", str(tmp_path / "d2")])
    assert calls[-1]["args"] == (Path("SRC"), tmp_path / "d2")
    assert result.stderr.startswith("seqat: note: `seqat feed SRC DST` is deprecated; use "
                                    f"`seqat feed SRC --out {tmp_path / 'd2'}`\n")
    both = cli.invoke(app, ["feed", "SRC", "x", "--out", "y"])
    neither = cli.invoke(app, ["feed", "SRC"])
    for bad in (both, neither):
        assert bad.exit_code == 2 and len(bad.stderr.splitlines()) == 1
        assert bad.stderr.startswith("seqat: error: ")
    assert len(calls) == 2


def _commands(group: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """Every command under ``group`` (click's, or the click Typer vendors)."""
    yield path, group
    for name, command in getattr(group, "commands", {}).items():
        yield from _commands(command, (*path, name))


COMMANDS = list(_commands(typer.main.get_command(app)))
#: Commands that write a new folder or file: their output is ``--out PATH``.
WRITERS = {"simulate", "run", "watch", "feed", "process", "bench", "dsm"}
#: Commands that work in an existing run folder: OUT is their first argument.
IN_RUN_FOLDER = {"reference", "report", "ortho", "serve"}


def test_out_is_an_option_where_a_command_writes_and_the_run_folder_otherwise() -> None:
    names = {path[-1] for path, _ in COMMANDS if path}
    assert names == WRITERS | IN_RUN_FOLDER
    for path, command in COMMANDS:
        if not path:
            continue
        options = {o for p in command.params if p.param_type_name == "option" for o in p.opts}
        arguments = [p.name for p in command.params if p.param_type_name == "argument"]
        if path[-1] in WRITERS:
            assert "--out" in options, path
        else:
            assert "--out" not in options and arguments[0] == "out", path


# ------------------------------------------------------------------ help texts


@pytest.mark.parametrize("path", [path for path, _ in COMMANDS], ids=lambda p: " ".join(p)
                         or "seqat")
def test_help_is_plain_and_shows_flags_as_flags(path: tuple[str, ...]) -> None:
    result = CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    text = result.stdout
    assert "``" not in text
    assert "<bool>" not in text
    command = dict(COMMANDS)[path]
    flags = [p for p in command.params if p.param_type_name == "option" and p.is_flag]
    for flag in flags:
        for line in text.splitlines():
            if f" {flag.opts[0]} " in line:
                assert "<" not in line, line
    # a paragraph's line breaks are the terminal's, not the docstring's: no line of the help
    # text ends mid-sentence far short of the width when the next one goes on with the sentence
    if command.help:
        for paragraph in command.help.split("\n\n"):
            assert "\n" not in paragraph


def test_ortho_eop_follows_the_run(tmp_path: Path) -> None:
    """--eop run (the default) is the run's own eop.csv whatever its method; another method's
    name is refused (it used to be taken for the run's eop.csv)."""
    from pipeline.ortho.stage import _eops

    table = object()
    assert _eops(tmp_path, "run", "sim", table) == (table, "sim")  # type: ignore[arg-type]
    assert _eops(tmp_path, "seq-f", "seq-f", table) == (table, "seq-f")  # type: ignore[arg-type]
    with pytest.raises(Exception, match="--eop seq-r: .* is a sim run"):
        _eops(tmp_path, "seq-r", "sim", table)  # type: ignore[arg-type]
    with pytest.raises(InputDataError, match="run `seqat reference"):
        _eops(tmp_path, "reference", "sim", table)  # type: ignore[arg-type]
