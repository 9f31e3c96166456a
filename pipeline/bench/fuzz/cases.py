"""The records of ``seqat bench fuzz``: one command's outcome, one case's, the summary."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from pipeline.bench.fuzz.mutations import Mutation


@dataclasses.dataclass(kw_only=True)
class CommandResult:
    name: str
    argv: list[str]
    exit_code: int | None  # None: timed out
    seconds: float
    first_stderr_line: str
    error_line: str
    traceback: bool
    absurd: list[str]
    stderr: str = ""


@dataclasses.dataclass(kw_only=True)
class CaseResult:
    seed: int
    index: int
    flight: str
    mutation: Mutation
    commands: list[CommandResult]
    inputs_changed: list[str]
    leftover: list[str]

    @property
    def defects(self) -> list[str]:
        out = []
        for c in self.commands:
            if c.exit_code not in (0, 2):
                out.append(f"{c.name}: exit {c.exit_code}")
            if c.traceback:
                out.append(f"{c.name}: traceback")
            out += [f"{c.name}: {a}" for a in c.absurd]
        out += [f"input changed: {p}" for p in self.inputs_changed]
        return out


@dataclasses.dataclass(kw_only=True)
class FuzzSummary:
    cases: int
    commands: int
    exit_0: int
    exit_2: int
    exit_other: int
    tracebacks: int
    absurd_outputs: int
    inputs_changed: int
    leftovers: int
    failing_cases: int


@dataclasses.dataclass(kw_only=True)
class FuzzReport:
    date: str
    seeds: list[int]
    cases_per_seed: int
    machine: object
    wall_s: float
    summary: FuzzSummary
    sample_data_changed: list[str]
    cases: list[CaseResult]


def summarise(cases: Sequence[CaseResult]) -> FuzzSummary:
    cmds = [c for case in cases for c in case.commands]
    return FuzzSummary(
        cases=len(cases), commands=len(cmds),
        exit_0=sum(c.exit_code == 0 for c in cmds), exit_2=sum(c.exit_code == 2 for c in cmds),
        exit_other=sum(c.exit_code not in (0, 2) for c in cmds),
        tracebacks=sum(c.traceback for c in cmds),
        absurd_outputs=sum(bool(c.absurd) for c in cmds),
        inputs_changed=sum(bool(case.inputs_changed) for case in cases),
        leftovers=sum(bool(case.leftover) for case in cases),
        failing_cases=sum(bool(case.defects) for case in cases))
