"""``seqat bench fuzz``: the mutation generator is deterministic and always changes something,
the output checks see absurd values, and a small seeded subset of the bench runs clean."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.bench.fuzz.checks import check_run_outputs
from pipeline.bench.fuzz.mutations import MUTATIONS, NotApplicable, tree_digest
from pipeline.bench.fuzz.suite import (
    FLIGHTS,
    SAMPLE_DATA,
    make_case,
    prepare_bases,
    run_fuzz_bench,
)


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return prepare_bases(SAMPLE_DATA, tmp_path_factory.mktemp("fuzz_bases"))


def _digest_of_copy(base: Path, root: Path, name: str) -> dict[str, str]:
    shutil.copytree(base, root / "input" / name, symlinks=True)
    d = tree_digest(root)
    shutil.rmtree(root)
    return d


def test_same_seed_and_index_give_the_same_case(bases: dict[str, Path], tmp_path: Path) -> None:
    for index in range(40):
        a = make_case(7, index, bases, tmp_path / f"a{index}")
        b = make_case(7, index, bases, tmp_path / f"b{index}")
        assert a[0] == b[0] and a[1] == b[1]
        assert tree_digest(tmp_path / f"a{index}") == tree_digest(tmp_path / f"b{index}")
        assert a[2].out.name == b[2].out.name
    other = [make_case(8, k, bases, tmp_path / f"c{k}")[1] for k in range(10)]
    same = [make_case(7, k, bases, tmp_path / f"d{k}")[1] for k in range(10)]
    assert other != same


def test_every_mutation_changes_the_case(bases: dict[str, Path], tmp_path: Path) -> None:
    seen: set[str] = set()
    for kind in MUTATIONS:
        for index in range(3):
            for name in FLIGHTS:
                root = tmp_path / f"{kind}_{index}_{name}"
                try:
                    flight, mutation, case = make_case(3, index, bases, root, kinds=(kind,),
                                                       flights=(name,))
                except (NotApplicable, RuntimeError):
                    shutil.rmtree(root, ignore_errors=True)
                    continue
                clean = _digest_of_copy(bases[flight], tmp_path / "clean", flight)
                changed = tree_digest(root) != clean or case.out.name != "run"
                assert changed, (kind, mutation)
                assert mutation.description
                seen.add(kind)
                shutil.rmtree(root)
    assert seen == set(MUTATIONS)  # every mutation applies to some sample flight


def _write(path: Path, text: str) -> None:
    path.write_text(text, encoding="utf-8")


def test_checks_flag_non_finite_and_absurd_outputs(tmp_path: Path) -> None:
    nav = ("image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg\n"
           "a,0,100,200,300,0,0,0\nb,1,110,200,300,0,0,0\n")
    eop_head = "image,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg,sx_m,sy_m,sz_m,somega_deg,sphi_deg," \
               "skappa_deg\n"
    good = eop_head + "a,100,200,300,0,0,0,nan,1,1,1,1,1\nb,110,200,300,0,0,0,1,1,1,1,1,1\n"
    points = "point,x_m,y_m,z_m,sx_m,sy_m,sz_m,n_obs\np1,105,200,0,1,1,1,2\n"
    _write(tmp_path / "nav.csv", nav)
    _write(tmp_path / "eop.csv", good)
    _write(tmp_path / "points.csv", points)
    _write(tmp_path / "run.json", json.dumps({"images": [], "totals": {"sigma0": 1.0}}))
    assert check_run_outputs(tmp_path) == []
    _write(tmp_path / "eop.csv", good.replace("b,110,200,300", "b,110,200,inf"))
    assert any("z_m" in p for p in check_run_outputs(tmp_path))
    _write(tmp_path / "eop.csv", good.replace("b,110,200,300", "b,1e7,200,300"))
    assert any("from its nav position" in p for p in check_run_outputs(tmp_path))
    _write(tmp_path / "eop.csv", good.replace(",1,1,1,1,1,1\n", ",1,-1,1,1,1,1\n"))
    assert any("sy_m" in p for p in check_run_outputs(tmp_path))
    _write(tmp_path / "eop.csv", good)
    _write(tmp_path / "points.csv", points.replace("105,200,0", "105,200,-5e4"))
    assert any("nav's extent" in p for p in check_run_outputs(tmp_path))
    _write(tmp_path / "points.csv", points)
    (tmp_path / "run.json").write_text('{"totals": {"sigma0": NaN}}', encoding="utf-8")
    assert any("run.json" in p for p in check_run_outputs(tmp_path))


#: The seeded subset run in the suite (the two fast sample flights).
SUBSET_SEED = 12
SUBSET_CASES = 6


def test_a_seeded_subset_exits_0_or_2_without_tracebacks_or_damage(tmp_path: Path) -> None:
    report = run_fuzz_bench(tmp_path / "bench", seeds=(SUBSET_SEED,), cases=SUBSET_CASES,
                            jobs=2, timeout_s=120, flights=("strip_demo", "autzen_rendered"))
    s = report.summary
    failing = [(c.index, c.mutation, c.defects) for c in report.cases if c.defects]
    assert s.cases == SUBSET_CASES and s.commands >= SUBSET_CASES
    assert (s.exit_other, s.tracebacks, s.absurd_outputs, s.inputs_changed) == (0, 0, 0, 0), \
        failing
    assert s.leftovers == 0, [c.leftover for c in report.cases if c.leftover]
    assert report.sample_data_changed == []
    for name in ("fuzz.csv", "fuzz.json", "fuzz.md"):
        assert (tmp_path / "bench" / name).is_file()
    rows = (tmp_path / "bench" / "fuzz.csv").read_text(encoding="utf-8").splitlines()
    assert rows[0].startswith("seed,case,flight,mutation") and len(rows) == s.commands + 1


def test_cli_replays_one_case_and_keeps_its_folder(bases: dict[str, Path],
                                                   tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    # the first case of seed 12 on strip_demo (fast), as the generator draws it
    k, mutation = next((k, m) for k in range(40)
                       for flight, m, _ in [make_case(12, k, bases, tmp_path / f"c{k}")]
                       if flight == "strip_demo")
    result = CliRunner().invoke(app, ["bench", "fuzz", "--seed", "12", "--case", str(k),
                                      "--out", str(tmp_path / "b")])
    assert result.exit_code == 0, result.output
    assert f"12/{k} strip_demo {mutation.kind} {mutation.target}: run=" in result.output
    assert mutation.description in result.output
    assert "$ seqat run CASE/input/strip_demo --out CASE/out/run" in result.output
    assert (tmp_path / "b" / "cases" / f"case_12_{k}" / "input").is_dir()
    doc = json.loads((tmp_path / "b" / "fuzz.json").read_text(encoding="utf-8"))
    assert [(c["seed"], c["index"]) for c in doc["cases"]] == [(12, k)]
