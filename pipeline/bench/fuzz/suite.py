"""``seqat bench fuzz``: seeded mutations of the sample flights, run as a user would (issue 13).

Each case ``(seed, index)`` copies one sample flight (``strip_demo``: observations and nav;
``autzen_rendered``: rendered images, geodetic nav, LiDAR, check points; ``seneca_mini``: real
JPEGs with the nav in EXIF/XMP, its first :data:`SENECA_IMAGES` images) to a temporary folder,
applies one mutation (:mod:`pipeline.bench.fuzz.mutations`) and runs the commands the mutated
file feeds, each as a subprocess (``python -m pipeline.cli``, the environment inherited) with a
timeout: ``seqat run`` always; ``seqat dsm`` and ``seqat ortho`` when the LiDAR or the flight
description of the Autzen flight was touched; ``seqat report`` when check points or truth were.

Scores (:class:`CommandResult`, :class:`CaseResult`): the exit code (0, 2 = bad input, anything
else or a timeout = a defect), a traceback on stderr (a defect), published outputs with
non-finite or absurd values (:mod:`pipeline.bench.fuzz.checks`; a defect), input files changed
(a digest of every entry that existed before the commands, compared after; a defect) and a
folder left behind by a failed command. A failing case is replayed with
``seqat bench fuzz --seed S --case K``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from pipeline.bench.common import load_average, machine
from pipeline.bench.fuzz.cases import CaseResult, CommandResult, FuzzReport, summarise
from pipeline.bench.fuzz.checks import check_dsm, check_json_file, check_run_outputs
from pipeline.bench.fuzz.mutations import CaseFolder, Mutation, case_rng, mutate, tree_digest
from seqat.errors import ConfigError

#: The repository's sample flights.
SAMPLE_DATA = Path(__file__).resolve().parents[3] / "sample_data"
#: Sample flights and their draw weights.
FLIGHTS: dict[str, float] = {"strip_demo": 0.35, "autzen_rendered": 0.4, "seneca_mini": 0.25}
#: Images of seneca_mini copied into a case (its 18 images of 3600 x 2700 px take ~16 s).
SENECA_IMAGES = 8
#: The Autzen flight's working CRS, for ``seqat dsm``.
AUTZEN_CRS = "EPSG:32610"
#: The command line module the cases run.
CLI = ("-m", "pipeline.cli")
DEFAULT_SEEDS = (1, 2, 3)
DEFAULT_CASES = 40
DEFAULT_TIMEOUT_S = 300.0


# --- the base flights ------------------------------------------------------------------------

def prepare_bases(sample_data: Path, work: Path) -> dict[str, Path]:
    """Copies of the sample flights the cases start from (``seneca_mini`` cut to its first
    :data:`SENECA_IMAGES` images)."""
    bases = {}
    for name in FLIGHTS:
        src = sample_data / name
        if not src.is_dir():
            raise ConfigError(f"{src}: sample flight not found (--sample-data)")
        dst = work / "base" / name
        if name == "seneca_mini":
            images = sorted((src / "images").glob("*.jpg"))[:SENECA_IMAGES]
            (dst / "images").mkdir(parents=True)
            for p in images:
                shutil.copy2(p, dst / "images" / p.name)
        else:
            shutil.copytree(src, dst, symlinks=True)
        bases[name] = dst
    return bases


def draw_flight(rng: object) -> str:
    import numpy as np

    names = list(FLIGHTS)
    w = np.array([FLIGHTS[n] for n in names])
    return names[int(rng.choice(len(names), p=w / w.sum()))]  # type: ignore[attr-defined]


def make_case(seed: int, index: int, bases: dict[str, Path], root: Path,
              kinds: tuple[str, ...] | None = None,
              flights: tuple[str, ...] | None = None) -> tuple[str, Mutation, CaseFolder]:
    """Case ``index`` of ``seed`` built in ``root`` (which must not exist): the flight copied
    to ``root/input/<name>`` and mutated."""
    rng = case_rng(seed, index)
    name = draw_flight(rng)
    if flights:
        name = flights[int(rng.integers(len(flights)))]
    case = CaseFolder(root=root, flight=root / "input" / name, out=root / "out" / "run")
    shutil.copytree(bases[name], case.flight, symlinks=True)
    mutation, case = mutate(case, rng, kinds)
    return name, mutation, case


# --- commands --------------------------------------------------------------------------------

def commands_for(name: str, mutation: Mutation, case: CaseFolder) -> list[tuple[str, list[str]]]:
    """``(command, arguments)`` the case runs; ``ortho`` and ``report`` only after a run that
    exited 0."""
    cmds = [("run", ["run", str(case.flight), "--out", str(case.out)])]
    target = mutation.target.lower()
    if name == "autzen_rendered":
        lidar = any(s in target for s in ("lidar", ".laz", ".las", "flight.yaml")) or \
            mutation.kind in ("rename_flight", "odd_path")
        if lidar:
            cmds.append(("dsm", ["dsm", str(case.flight / "lidar" / "surface.laz"), "--out",
                                 str(case.root / "dsm out" / "dsm.tif"), "--crs", AUTZEN_CRS]))
            cmds.append(("ortho", ["ortho", str(case.out), "--no-progress"]))
        if "checkpoint" in target or "truth" in target or "flight.yaml" in target:
            cmds.append(("report", ["report", str(case.out)]))
    elif name == "strip_demo" and ("truth" in target or "flight.yaml" in target):
        cmds.append(("report", ["report", str(case.out)]))
    return cmds


def _first_line(text: str) -> str:
    return next((line.strip() for line in text.splitlines() if line.strip()), "")


def _error_line(text: str) -> str:
    for line in text.splitlines():
        if line.startswith("seqat: ") or line.startswith("Error") or "Traceback" in line:
            return line.strip()
    return ""


def run_command(argv: list[str], timeout_s: float, cwd: Path) -> tuple[int | None, str, float]:
    env = dict(os.environ)
    env.pop("SEQAT_DEBUG", None)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *CLI, *argv], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        _, err = proc.communicate(timeout=timeout_s)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        code = None
    return code, err.decode("utf-8", "replace"), time.perf_counter() - t0


def _check(name: str, case: CaseFolder) -> list[str]:
    try:
        return _check_outputs(name, case)
    except Exception as err:  # noqa: BLE001 - an output the checks cannot read is a finding
        return [f"outputs not checkable: {type(err).__name__}: {err}"]


def _check_outputs(name: str, case: CaseFolder) -> list[str]:
    if name == "run":
        return check_run_outputs(case.out)
    if name == "dsm":
        return check_dsm(case.root / "dsm out" / "dsm.tif")
    if name == "ortho":
        return check_json_file(case.out / "ortho.json")
    if name == "report":
        return check_json_file(case.out / "report.json")
    return []


def run_case(seed: int, index: int, bases: dict[str, Path], work: Path, timeout_s: float,
             kinds: tuple[str, ...] | None = None, flights: tuple[str, ...] | None = None,
             keep: bool = False) -> CaseResult:
    root = work / f"case_{seed}_{index}"
    if root.exists():
        shutil.rmtree(root)
    try:
        name, mutation, case = make_case(seed, index, bases, root, kinds, flights)
        before = tree_digest(root)
        results: list[CommandResult] = []
        leftover: list[str] = []
        run_ok = False
        for cmd, args in commands_for(name, mutation, case):
            if cmd in ("ortho", "report") and not run_ok:
                continue
            existed = case.out.exists() or case.out.is_symlink()
            dsm_dir = case.root / "dsm out"
            code, err, seconds = run_command(args, timeout_s, root)
            err = err.replace(str(root), "CASE")
            absurd = _check(cmd, case) if code == 0 else []
            if cmd == "run":
                run_ok = code == 0
                if code != 0 and not existed and case.out.exists():
                    leftover.append(f"run: {case.out.name}/ left by a failed run")
            if cmd == "dsm" and code != 0 and dsm_dir.exists() and any(dsm_dir.iterdir()):
                leftover.append("dsm: files left by a failed dsm")
            results.append(CommandResult(
                name=cmd, argv=[a.replace(str(root), "CASE") for a in args], exit_code=code,
                seconds=round(seconds, 2), first_stderr_line=_first_line(err),
                error_line=_error_line(err), traceback="Traceback (most recent call last)" in err,
                absurd=absurd, stderr=err if keep else ""))
        after = tree_digest(root)
        changed = sorted(k for k, v in before.items() if after.get(k) != v)
        return CaseResult(seed=seed, index=index, flight=name, mutation=mutation,
                          commands=results, inputs_changed=changed, leftover=leftover)
    finally:
        if not keep and root.exists():
            shutil.rmtree(root, ignore_errors=True)


def run_fuzz_bench(out: Path, *, seeds: Sequence[int] = DEFAULT_SEEDS,
                   cases: int = DEFAULT_CASES, only: Sequence[int] = (),
                   timeout_s: float = DEFAULT_TIMEOUT_S, jobs: int = 1,
                   kinds: tuple[str, ...] | None = None, flights: tuple[str, ...] | None = None,
                   sample_data: Path = SAMPLE_DATA, keep: bool = False,
                   progress: Callable[[CaseResult], None] | None = None) -> FuzzReport:
    """Run ``cases`` cases per seed (or only the case indices ``only``), write
    ``out/fuzz.csv``, ``fuzz.json`` and ``fuzz.md`` and return the report. ``keep`` keeps
    each case's folder (and stderr) under ``out/cases/``."""
    from pipeline.bench.fuzz.report import write_outputs

    load0 = load_average()
    t0 = time.perf_counter()
    sample_before = tree_digest(sample_data)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="seqat-fuzz-"))
    work = out / "cases" if keep else tmp
    try:
        bases = prepare_bases(sample_data, tmp)
        todo = [(s, k) for s in seeds for k in (only or range(cases))]
        results: list[CaseResult] = []

        def one(sk: tuple[int, int]) -> CaseResult:
            r = run_case(sk[0], sk[1], bases, work, timeout_s, kinds, flights, keep)
            if progress is not None:
                progress(r)
            return r

        with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
            results = list(pool.map(one, todo))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    sample_after = tree_digest(sample_data)
    report = FuzzReport(
        date=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        seeds=list(seeds), cases_per_seed=len(only) or cases, machine=machine(load0),
        wall_s=round(time.perf_counter() - t0, 1), summary=summarise(results),
        sample_data_changed=sorted(k for k, v in sample_before.items()
                                   if sample_after.get(k) != v),
        cases=results)
    write_outputs(report, out)
    return report


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="seqat bench fuzz", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_fuzz"))
    ap.add_argument("--seed", type=int, action="append",
                    help=f"seed (repeat; default {list(DEFAULT_SEEDS)})")
    ap.add_argument("--cases", type=int, default=DEFAULT_CASES, help="cases per seed")
    ap.add_argument("--case", type=int, action="append",
                    help="run only this case index (repeat): the replay of a failing case")
    ap.add_argument("--timeout-s", type=float, default=DEFAULT_TIMEOUT_S,
                    help="timeout of each command")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once")
    ap.add_argument("--kind", action="append", help="only these mutations (repeat)")
    ap.add_argument("--flight", action="append", choices=list(FLIGHTS), type=str.lower,
                    help="only these sample flights (repeat)")
    ap.add_argument("--sample-data", type=Path, default=SAMPLE_DATA)
    ap.add_argument("--keep", action="store_true",
                    help="keep each case's folder and stderr in OUT/cases/ (default with --case)")
    args = ap.parse_args(list(argv))
    if args.cases < 1 or args.jobs < 1 or args.timeout_s <= 0:
        raise ConfigError("seqat bench fuzz: --cases, --jobs and --timeout-s must be positive")
    return args


def main(argv: Sequence[str], progress: Callable[[CaseResult], None] | None = None
         ) -> FuzzReport:
    """``seqat bench fuzz ARGS``: parse, run, write; the CLI prints the tables."""
    from pipeline.bench.fuzz.mutations import MUTATIONS

    args = parse_args(argv)
    if args.kind and not set(args.kind) <= set(MUTATIONS):
        raise ConfigError(f"seqat bench fuzz: --kind: expected one of {', '.join(MUTATIONS)}")
    return run_fuzz_bench(
        args.out, seeds=tuple(args.seed or DEFAULT_SEEDS), cases=args.cases,
        only=tuple(args.case or ()), timeout_s=args.timeout_s, jobs=args.jobs,
        kinds=tuple(args.kind) if args.kind else None,
        flights=tuple(args.flight) if args.flight else None, sample_data=args.sample_data,
        keep=args.keep or bool(args.case), progress=progress)
