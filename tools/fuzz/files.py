"""``files``: corrupt inputs and refused outputs for every command-line tool.

For each tool (:data:`.tools.TOOLS`) ``per_tool`` cases are generated from the valid
corpus (:mod:`.corpus`) by the generators of :mod:`.corrupt_data` and
:mod:`.corrupt_vision`, each in a folder of its own, and the tool is run on each, in this
process (its ``main``) or as a subprocess (``--subprocess``; always for cases that must run
as an unprivileged user or might exhaust memory). Checked per run:

* **traceback**: an exception escaped ``main`` (or ``Traceback`` in its stderr);
* **exit code** against the documented ones for that input (a timeout counts as wrong);
* **names the file**: a refusal (non-zero exit) must name the file (and the line, where
  the input has lines);
* **overwritten**: a protected file (inputs, an existing output) changed;
* **left behind**: anything new in the case folder that is not an output of a successful
  run (hidden temporary or ``*.partial-*`` files included); and leftovers of an earlier
  killed run that are neither removed nor reported.
"""
from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import corrupt_data, corrupt_vision
from .corpus import build_corpus
from .filecase import FileCase, read_only
from .report import Target, at_least, at_most, table
from .tools import TOOLS, fingerprint, listing, run_in_process, run_subprocess
from .messages import fresh_domain

GENERATORS = {
    'replay': corrupt_data.replay_case,
    'eval_bag': corrupt_data.eval_bag_case,
    'eval_smartloc': corrupt_data.eval_smartloc_case,
    'convert': corrupt_data.convert_case,
    'mapdb_build': corrupt_vision.mapdb_build_case,
    'mapdb_query': corrupt_vision.mapdb_query_case,
    'record': corrupt_vision.record_case,
}
#: Tools whose runs start rclpy (their own ROS domain, set for the run).
ROS_TOOLS = ('replay', 'record')


@dataclass
class FilesConfig:
    """A ``files`` run (the CLI's options)."""

    seed: int = 1
    per_tool: int = 100
    tools: list | None = None
    subprocess: bool = False
    work_dir: str | None = None
    domain: int | None = None
    timeout_s: float = 180.0
    target_per_tool: int = 100


@dataclass
class CaseResult:
    """One tool run and what the checks found."""

    tool: str
    name: str
    expect: tuple
    code: int | None
    seconds: float
    traceback: bool = False
    exception: str = ''
    wrong_code: bool = False
    unnamed: bool = False
    no_line: bool = False
    overwritten: list = None
    left_behind: list = None
    stale_kept: list = None
    check: str | None = None
    stderr_tail: str = ''
    kit_error: str | None = None

    @property
    def problems(self) -> list[str]:
        if self.kit_error:
            return [f'kit error ({self.kit_error})']
        out = []
        if self.traceback:
            out.append('traceback' + (f' ({self.exception})' if self.exception else ''))
        if self.wrong_code:
            out.append(f'exit {self.code}, documented {"/".join(map(str, self.expect))}')
        if self.unnamed:
            out.append('error does not name the file')
        if self.no_line:
            out.append('error does not name the line')
        if self.overwritten:
            out.append(f'overwrote {len(self.overwritten)}')
        if self.left_behind:
            out.append(f'left {len(self.left_behind)} behind')
        if self.stale_kept:
            out.append(f'{len(self.stale_kept)} old partials kept unreported')
        if self.check:
            out.append(self.check)
        return out


def _env(cfg: FilesConfig, tool: str, folder: Path) -> dict:
    env = {'ROS_LOG_DIR': str(folder.parent / 'ros_log'), 'OPENBLAS_NUM_THREADS': '1'}
    if tool in ROS_TOOLS:
        env.update(ROS_DOMAIN_ID=str(cfg.domain if cfg.domain is not None
                                     else fresh_domain()),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return env


def run_case(cfg: FilesConfig, case: FileCase, folder: Path) -> CaseResult:
    """Run one case and check it."""
    before = {p: fingerprint(p) for p in case.protect}
    seen = {str(w): listing(w) for w in case.watch}
    env = _env(cfg, case.tool, folder)
    with read_only(case.read_only) as locked:
        if not locked:
            return CaseResult(case.tool, case.name, case.expect, None, 0.0,
                              kit_error='not run: the folder could not be made read-only')
        if cfg.subprocess or case.isolate:
            outcome = run_subprocess(case.tool, case.argv, env, cfg.timeout_s)
        else:
            outcome = run_in_process(case.tool, case.argv, env)
    text = outcome.stderr + outcome.stdout
    res = CaseResult(case.tool, case.name, case.expect, outcome.code, outcome.seconds,
                     traceback=outcome.traceback, exception=outcome.exception,
                     stderr_tail=outcome.stderr.strip()[-300:])
    res.wrong_code = outcome.timed_out or outcome.code not in case.expect
    if outcome.code not in (0, None) and case.names:
        res.unnamed = not any(n in text for n in case.names)
        if case.line is not None:
            res.no_line = not any(f'{n}:{case.line}' in text for n in case.names) and \
                f'line {case.line}' not in text
    res.overwritten = [str(p) for p, fp in before.items() if fingerprint(p) != fp]
    allowed = {str(a) for a in case.allowed}
    left = []
    for w in case.watch:
        for rel in sorted(listing(w) - seen[str(w)]):
            full = str(Path(w) / rel)
            if outcome.code == 0 and any(full == a or full.startswith(a + '/')
                                         for a in allowed):
                continue
            left.append(rel)
    res.left_behind = left
    res.stale_kept = [str(p) for p in case.stale
                      if p.exists() and p.name not in text and 'partial' not in text]
    if outcome.code == 0 and case.check is not None:
        try:
            res.check = case.check(outcome)
        except Exception as err:     # noqa: BLE001 - the output itself is broken
            res.check = f'output unreadable: {type(err).__name__}: {err}'[:200]
    return res


def run_files(cfg: FilesConfig, log=print) -> dict:
    """Every tool on ``per_tool`` corrupt inputs; the figures and targets."""
    t0 = time.monotonic()
    root = Path(cfg.work_dir or tempfile.mkdtemp(prefix='gnsscam_fuzz_files_'))
    root.mkdir(parents=True, exist_ok=True)
    root.chmod(0o755)
    corpus = build_corpus(root, cfg.seed)
    tools = cfg.tools or list(GENERATORS)
    unknown = set(tools) - set(GENERATORS)
    if unknown:
        raise ValueError(f'unknown tools {sorted(unknown)}; known: {sorted(GENERATORS)}')
    results: list[CaseResult] = []
    for tool in tools:
        rng = np.random.default_rng([cfg.seed, sorted(GENERATORS).index(tool)])
        t_tool = time.monotonic()
        for i in range(cfg.per_tool):
            folder = root / tool / f'{i:04d}'
            if folder.exists():
                shutil.rmtree(folder)
            folder.mkdir(parents=True)
            case = GENERATORS[tool](i, rng, corpus, folder)
            try:
                results.append(run_case(cfg, case, folder))
            except Exception as err:     # noqa: BLE001 - the kit's own failure, reported
                results.append(CaseResult(tool, case.name, case.expect, None, 0.0,
                                          kit_error=f'{type(err).__name__}: {err}'))
        log(f'files: {tool}: {cfg.per_tool} cases in {time.monotonic() - t_tool:.1f} s')
    return summarize(cfg, tools, results, time.monotonic() - t0, root)


def summarize(cfg: FilesConfig, tools: list[str], results: list[CaseResult],
              seconds: float, root: Path) -> dict:
    per_tool = {}
    for tool in tools:
        rs = [r for r in results if r.tool == tool]
        per_tool[tool] = {
            'program': ' '.join([TOOLS[tool][0], *TOOLS[tool][2]]),
            'cases': len(rs), 'tracebacks': sum(r.traceback for r in rs),
            'wrong_exit_code': sum(r.wrong_code for r in rs),
            'unnamed': sum(r.unnamed for r in rs), 'no_line': sum(r.no_line for r in rs),
            'overwritten': sum(bool(r.overwritten) for r in rs),
            'left_behind': sum(bool(r.left_behind) for r in rs),
            'stale_kept': sum(bool(r.stale_kept) for r in rs),
            'check_failed': sum(bool(r.check) for r in rs),
            'kit_errors': sum(bool(r.kit_error) for r in rs),
            'ok': sum(not r.problems for r in rs),
            'seconds': float(sum(r.seconds for r in rs)),
        }
    totals = {k: sum(t[k] for t in per_tool.values())
              for k in ('tracebacks', 'wrong_exit_code', 'unnamed', 'no_line', 'overwritten',
                        'left_behind', 'stale_kept', 'check_failed', 'kit_errors')}
    fewest = min((t['cases'] for t in per_tool.values()), default=0)
    by_name: dict[str, dict] = {}
    for r in results:
        if not r.problems:
            continue
        key = f'{r.tool}:{r.name}'
        entry = by_name.setdefault(key, {'case': key, 'runs': 0, 'problems': {},
                                         'example': r.stderr_tail})
        entry['runs'] += 1
        for p in r.problems:
            short = p.split(' (')[0]
            entry['problems'][short] = entry['problems'].get(short, 0) + 1
    targets = [
        at_least(f'corrupt inputs per tool >= {cfg.target_per_tool} (fewest)', fewest,
                 cfg.target_per_tool),
        at_most('tracebacks == 0', totals['tracebacks'], 0),
        at_most('exit codes as documented (mismatches == 0)', totals['wrong_exit_code'], 0),
        at_most('every error names the file (and line)', totals['unnamed']
                + totals['no_line'], 0),
        at_most('nothing overwritten', totals['overwritten'], 0),
        at_most('nothing left behind', totals['left_behind'] + totals['stale_kept'], 0),
        at_most('outputs of accepted inputs sane', totals['check_failed'], 0),
        at_most('every case run (kit errors == 0)', totals['kit_errors'], 0),
    ]
    return {'config': asdict(cfg), 'per_tool': per_tool, 'totals': totals,
            'failing_cases': sorted(by_name.values(), key=lambda e: -e['runs']),
            'cases': [dict(asdict(r), problems=r.problems) for r in results],
            'seconds': seconds, 'work_dir': str(root),
            'targets': [t.as_dict() for t in targets]}


def print_files(result: dict) -> list[Target]:
    rows = [[tool, t['program'], t['cases'], t['ok'], t['tracebacks'], t['wrong_exit_code'],
             t['unnamed'], t['no_line'], t['overwritten'], t['left_behind'] + t['stale_kept'],
             t['check_failed'], t['kit_errors'], t['seconds']]
            for tool, t in result['per_tool'].items()]
    print(table(['tool', 'command', 'cases', 'ok', 'tracebacks', 'wrong exit', 'file unnamed',
                 'line unnamed', 'overwrote', 'left behind', 'bad output', 'kit error', 's'],
                rows))
    failing = result['failing_cases']
    if failing:
        print(f'\ncases with a problem ({len(failing)} kinds; first 40):')
        rows = [[f['case'], f['runs'],
                 ', '.join(f'{k} x{v}' for k, v in f['problems'].items()),
                 ' '.join(f['example'].split())[-70:]] for f in failing[:40]]
        print(table(['case', 'runs', 'problems', 'stderr (end)'], rows))
    print(f"\n{sum(t['cases'] for t in result['per_tool'].values())} runs in "
          f"{result['seconds']:.0f} s" if math.isfinite(result['seconds']) else '')
    return [Target(**t) for t in result['targets']]
