"""``python -m tools.fuzz {messages,processes,files} [--seed S] [--json FILE]``.

Each subcommand prints its figures as tables and ends with one verdict line (PASS only when
every target of the issue holds; each target with its figure). ``--json FILE`` also writes
every figure to a new file (never over an existing one). Progress goes to stderr.

Exit codes: 0 the campaign ran (whatever its verdict: the verdict line says), 2 bad usage
or an existing ``--json``, 1 the campaign itself failed (e.g. the nodes never started).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import fields
from pathlib import Path

from gnsscam_ros.io.atomic import OutputExistsError, write_json_atomic

from .report import Target, fmt, table, targets_table, verdict_line
from .files import FilesConfig, print_files, run_files
from .messages import MessagesConfig, run_messages
from .processes import ProcessesConfig, print_processes, run_processes

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument('--seed', type=int, default=1, help='seed of everything (default 1)')
    p.add_argument('--json', type=Path, help='also write the figures to this new file')
    p.add_argument('--work-dir', help='keep logs and generated inputs here (default: a '
                   'new temporary folder)')
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='python -m tools.fuzz',
                                     description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    m = sub.add_parser('messages', help='malformed and mutated messages on every input '
                       'topic of a running pipeline_node')
    _common(m)
    m.add_argument('--duration-s', type=float, default=60.0, help='drive length [s]')
    m.add_argument('--warmup-s', type=float, default=15.0,
                   help='clean drive before the faults [s]')
    m.add_argument('--tail-s', type=float, default=20.0,
                   help='clean drive after the faults (recovery) [s]')
    m.add_argument('--structured', type=int, default=1000,
                   help='structured malformed messages (default %(default)s)')
    m.add_argument('--mutations', type=int, default=200,
                   help='random mutations of valid messages (default %(default)s)')
    m.add_argument('--light', action='store_true',
                   help='leave out the heavy cases (1,000/10,000 satellites, 8000x8000 '
                   'image)')
    m.add_argument('--no-camera', action='store_true',
                   help='no camera frames (and no faults on camera/image_raw)')
    m.add_argument('--no-floods', action='store_true',
                   help='no floods (three times a subscription depth of valid messages)')
    m.add_argument('--no-prestart', action='store_true',
                   help='no negative stamps before the first valid message')
    m.add_argument('--no-clean-pass', action='store_true',
                   help='skip the clean pass (no RSS or recovery baseline)')
    m.add_argument('--memory-limit-mb', type=float, default=4096.0,
                   help='resident memory at which the kit kills pipeline_node (a crash of '
                   'the kind that caused it; protects a shared machine) [MB]')
    m.add_argument('--hang-s', type=float, default=10.0,
                   help='no integrity_risk for this long is a hang (default %(default)s)')
    m.add_argument('--burst', type=int, default=10, help='most messages per burst')
    m.add_argument('--only', nargs='+', metavar='TEXT',
                   help='play only the structured cases whose kind (topic:name) contains '
                   'one of these (to reproduce one), e.g. satellites_1000')
    m.add_argument('--gnss-rate-hz', type=float, default=1.0,
                   help='GNSS epochs per second of the drive (more epochs: more slots, '
                   'fewer kinds share one)')
    m.add_argument('--particles', type=int, help="fusion_node's n_particles")
    m.add_argument('--acquisition-particles', type=int,
                   help="fusion_node's acquisition_particles")
    p = sub.add_parser('processes', help='SIGKILL and restart of each node mid-replay')
    _common(p)
    p.add_argument('--duration-s', type=float, default=90.0, help='drive length [s]')
    p.add_argument('--nodes', nargs='+', default=None,
                   help='nodes to kill (default: gnss_node imu_node camera_node '
                   'fusion_node)')
    p.add_argument('--rate', type=float, default=2.0,
                   help='replay speed, a multiple of real time (default %(default)s)')
    p.add_argument('--down-s', type=float, default=3.0,
                   help='stamp time a killed node stays down [s]')
    p.add_argument('--no-camera', action='store_true', help='no camera_node')
    f = sub.add_parser('files', help='corrupt files for each command-line tool')
    _common(f)
    f.add_argument('--per-tool', type=int, default=100,
                   help='corrupt inputs per tool (default %(default)s)')
    f.add_argument('--tools', nargs='+', default=None, help='tools to try (default: all)')
    f.add_argument('--subprocess', action='store_true',
                   help='run every tool as a subprocess (default: in this process where '
                   'that is safe, a subprocess where it is not)')
    return parser


def _config(cls, args, **extra):
    names = {f.name for f in fields(cls)}
    values = {k: v for k, v in vars(args).items() if k in names}
    values.update({k: v for k, v in extra.items() if k in names})
    return cls(**values)


# ====================================================================== printing
def print_messages(result: dict, out=sys.stdout) -> list[Target]:
    passes = result['passes']
    rows = []
    for label, f in passes.items():
        rows.append([label, f['epochs'], f['answered'], f['unanswered'], f['crashes'],
                     f['hangs'], f['longest_silence_s'], f['rss_start_mb'],
                     f['rss_peak_mb'], f['rss_end_mb'], f['rejections_of_valid_input'],
                     f['ok_verdicts'], f['misleading_ok'], f['error']['median_m'],
                     f['exit_code_at_stop'], f['seconds']])
    print(table(['pass', 'epochs', 'answered', 'unanswered', 'crashes', 'hangs',
                 'silence max s', 'RSS start MB', 'RSS peak MB', 'RSS end MB',
                 'valid refused', 'OK', 'misleading OK', 'err2D med m', 'exit', 's'], rows),
          file=out)
    m = result['messages']
    print(f"\nmalformed messages: {m['malformed']} ({m['structured']} structured, "
          f"{m['mutations']} mutations, less {m['valid_after_mutation']} valid after "
          f"mutation; {m['unsendable']} not serialisable here); {m['floods']} valid "
          "messages in floods", file=out)
    rows = [[t, r['structured'], r['mutations'], r['valid_after_mutation'], r['floods'],
             r['delivered'], r['refused'], r['uncounted_loss'], r['silently_accepted'],
             r['crashes']]
            for t, r in result['by_topic'].items()]
    print(table(['topic', 'structured', 'mutations', 'valid after mutation', 'flood',
                 'delivered', 'refused (counted)', 'lost uncounted', 'accepted silently',
                 'crashes'], rows), file=out)
    f = passes['faults']
    print(f"OK verdicts on injected epochs: {f['ok_on_injected_epochs']} "
          f"({f['ok_on_injected_scored']} scored against the truth, "
          f"{f['misleading_ok_on_injected']} with the error above the alert limit, max "
          f"{fmt(f['ok_on_injected_error_max_m'])} m; {f['ok_on_injected_unscored']} "
          "unscored)", file=out)
    bad = [k for k in result['kinds'].values() if k['outcome'] not in ('ok', 'not tried')]
    bad.sort(key=lambda k: (-k['crashes'], -k['blocks'], -k['uncounted'], k['kind']))
    if bad:
        print(f'\nkinds with a failure ({len(bad)} of {len(result["kinds"])}):', file=out)
        print(table(['kind', 'sent', 'outcome', 'max burst s'],
                    [[k['kind'], k['sent'], k['outcome'], k['max_burst_s']]
                     for k in bad[:40]]), file=out)
        if len(bad) > 40:
            print(f'... and {len(bad) - 40} more (--json has all)', file=out)
    issue = [k for k in result['kinds'].values() if k['issue']]
    print("\nthe issue's single-message cases (refusals as the nodes counted them):",
          file=out)
    print(table(['kind', 'sent', 'outcome', 'refused as'],
                [[k['kind'], k['sent'], k['outcome'],
                  ', '.join(f'{r} {n}' for r, n in k['reasons'].items())[:60]]
                 for k in issue]), file=out)
    for crash in result['crashes'][:20]:
        also = (f"; earlier faults on the failed node's inputs: "
                f"{', '.join(crash['suspects'][:3])}" if crash.get('suspects') else '')
        print(f"crash after {crash['kind']} ({crash['during']}, exit {crash['exit_code']}"
              f"{also}): {crash['cause']}", file=out)
    for block in result['blocks'][:20]:
        print(f"block from epoch {block['epoch']} ({block['epochs_unanswered']} epochs "
              f"without a verdict) after {', '.join(block['kinds']) or 'valid input'}",
              file=out)
    restarts = passes['faults']['restarts']
    print(f"\nrecovery after the last fault: {fmt(result['recovery_s'])} s (stamp time); "
          f"RSS at the end vs the clean pass: {fmt(result['rss_rel_to_clean'])}"
          + (f' (pipeline_node restarted {restarts} times: not the same process)'
             if restarts else ''), file=out)
    return [Target(**t) for t in result['targets']]


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.json is not None and args.json.exists():
        print(f'fuzz: {args.json} exists; not overwriting', file=sys.stderr)
        return EXIT_USAGE
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr,
                                                                 flush=True))
    try:
        if args.command == 'messages':
            cfg = _config(MessagesConfig, args, heavy=not args.light,
                          camera=not args.no_camera, clean_pass=not args.no_clean_pass,
                          prestart=not args.no_prestart, floods=not args.no_floods)
            result = run_messages(cfg, log)
            targets = print_messages(result)
        elif args.command == 'processes':
            cfg = _config(ProcessesConfig, args, camera=not args.no_camera)
            result = run_processes(cfg, log)
            targets = print_processes(result)
        else:
            cfg = _config(FilesConfig, args)
            result = run_files(cfg, log)
            targets = print_files(result)
    except RuntimeError as err:
        print(f'fuzz {args.command}: {err}', file=sys.stderr)
        return EXIT_FAILED
    print()
    print(targets_table(targets))
    line = verdict_line(args.command, targets)
    print(line)
    result['verdict'] = line
    if args.json is not None:
        try:
            write_json_atomic(args.json, result)
        except (OSError, OutputExistsError) as err:
            print(f'fuzz: cannot write {args.json}: {err}', file=sys.stderr)
            return EXIT_USAGE
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
