"""Never crash, never lie: the command-line tools against corrupt input and faulty output.

Tables of corrupt inputs per tool, each run in-process through the tool's ``main(argv)``:
the documented exit code, one error line naming the file (and line where there is one), no
traceback, nothing overwritten, no temporary or partial file left behind. The ROS tools
(``gnsscam_replay``, ``gnsscam_record``) are in test_tools_robustness_ros.py.
"""
import functools
import os
import shutil
import signal
import socket
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT, wait_until

from gnsscam_ros.bags.convert_cli import main as convert_main
from gnsscam_ros.evaluation.cli import main as eval_main
from gnsscam_ros.io import partials
from gnsscam_ros.io.atomic import write_csv_atomic, write_json_atomic, write_npz_atomic
from gnsscam_ros.vision import mapdb_cli
from gnsscam_ros.vision.database import MapDatabase
from gnsscam_ros.vision.synthetic import synthetic_scene
from tools.fuzz.corrupt_inputs import (BAD_NUMBERS, GOOD_INPUT, GOOD_TRUTH, ODOM, POINT, PR,
                                       assert_refused, dead_pid, hidden_leftovers,
                                       image_cases, librsf_cases, line_with, snapshot,
                                       unwritable_folder)


def run(main, argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ========================================================== gnsscam_eval smartloc
def _write_run(folder: Path, text: str, truth: str = ''):
    folder.mkdir(parents=True, exist_ok=True)
    inp = folder / 'run_Input.txt'
    # latin-1: one byte per character, so the "binary" and "latin1" cases stay invalid
    # UTF-8 (ASCII lines are unchanged).
    inp.write_bytes(text.encode('latin-1'))
    gt = None
    if truth:
        gt = folder / 'run_GT.txt'
        gt.write_text(truth)
    return inp, gt


def _field_cases():
    """Every field of every record type with every bad number: (tag, file, line)."""
    for tag, fields in (('pseudorange3', PR), ('odom3', ODOM), ('point3', POINT)):
        for index in range(1, len(fields)):
            for value in BAD_NUMBERS:
                time_s = value if index == 1 else '1'
                yield tag, index, value, line_with(fields, index, value, time=time_s)


@pytest.mark.slow
def test_librsf_bad_numbers_refused_with_file_and_line(tmp_path, capsys, monkeypatch):
    """360 lines with NaN, inf, 1e308, 1e400, garbage in each field of each record: exit
    3 at load, file:line named, with and without --json, no JSON written."""
    # Building the argparse parser is 90 % of a refused run: build it once (parse_args
    # keeps no state between calls), so that the table stays fast.
    from gnsscam_ros.evaluation import cli
    monkeypatch.setattr(cli, 'build_parser', functools.lru_cache(cli.build_parser))
    tried = 0
    for k, (tag, index, value, line) in enumerate(_field_cases()):
        folder = tmp_path / f'case{k}'
        if tag == 'point3':
            inp, gt = _write_run(folder, GOOD_INPUT, GOOD_TRUTH + line)
            where = f'{gt}:2:'
        else:
            inp, gt = _write_run(folder, GOOD_INPUT + line)
            where = f'{inp}:3:'
        argv = ['smartloc', '--input', inp, '--quiet'] + (['--truth', gt] if gt else [])
        # Alternate with and without --json: the exit code must not depend on it.
        js = folder / 'out.json'
        if k % 2:
            argv += ['--json', js]
        code, out, err = run(eval_main, argv, capsys)
        line_out = assert_refused(code, err, 3, 'gnsscam_eval', where, tag)
        assert not js.exists() and out == '', (tag, index, value, line_out)
        assert not hidden_leftovers(folder)
        tried += 1
    assert tried == 360


@pytest.mark.slow
@pytest.mark.parametrize('case', librsf_cases(), ids=lambda c: c[0])
def test_librsf_malformed_files(tmp_path, capsys, case):
    name, text, truth, expected = case
    inp, gt = _write_run(tmp_path / 'run', text, truth)
    before = snapshot(tmp_path)
    argv = ['smartloc', '--input', inp, '--quiet'] + (['--truth', gt] if gt else [])
    code, out, err = run(eval_main, argv + ['--json', tmp_path / 'run' / 'x.json'], capsys)
    line = assert_refused(code, err, 3, 'gnsscam_eval', gt if 'truth' in name else inp)
    assert expected in line
    assert snapshot(tmp_path) == before                 # nothing written, nothing left


def test_librsf_missing_folder_and_special_files(tmp_path, capsys):
    cases = [(tmp_path / 'absent_Input.txt', 'cannot open'),
             (tmp_path, 'cannot open'),                     # a folder as --input
             (Path('/dev/null'), 'no pseudorange3 lines'),
             (Path('/dev/zero'), 'longer than')]            # endless NUL bytes: bounded
    for path, expected in cases:
        code, _, err = run(eval_main, ['smartloc', '--input', path, '--quiet'], capsys)
        assert expected in assert_refused(code, err, 3, 'gnsscam_eval', path)
    code, _, err = run(eval_main, ['smartloc', tmp_path / 'nothing', '--quiet'], capsys)
    assert_refused(code, err, 3, 'gnsscam_eval', tmp_path / 'nothing')


def test_eval_never_overwrites_and_reports_unwritable_output(tmp_path, capsys):
    js = tmp_path / 'result.json'
    js.write_text('keep me\n')
    code, _, err = run(eval_main, ['smartloc', SMARTLOC_EXCERPT, '--json', js, '--quiet'],
                       capsys)
    assert_refused(code, err, 4, 'gnsscam_eval', js)
    assert js.read_text() == 'keep me\n'
    # A folder nobody may write in, a parent that is a file: refused before the run
    # (exit 4) naming the file, nothing left behind.
    for bad in (unwritable_folder(tmp_path) / 'result.json', js / 'result.json'):
        for option in ('--json', '--epochs-csv'):
            code, out, err = run(eval_main, ['smartloc', SMARTLOC_EXCERPT, option, bad,
                                             '--quiet'], capsys)
            assert_refused(code, err, 4, 'gnsscam_eval', bad)
            assert out == '' and not bad.exists()
    assert not hidden_leftovers(tmp_path)


# ===================================================== gnsscam_convert (smartloc input)
def _convert_cases():
    """The malformed files, and a sample of the bad numbers (one value per field)."""
    cases = [(c[0], c[1], c[2]) for c in librsf_cases()]
    for k, (tag, index, value, line) in enumerate(_field_cases()):
        # Two values per field, a different pair from field to field.
        if k % len(BAD_NUMBERS) in (index % len(BAD_NUMBERS), (index + 5) % len(BAD_NUMBERS)):
            if tag == 'point3':
                cases.append((f'{tag}-{index}-{value}', GOOD_INPUT, GOOD_TRUTH + line))
            else:
                cases.append((f'{tag}-{index}-{value}', GOOD_INPUT + line, ''))
    return cases


def test_convert_refuses_bad_librsf_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    from gnsscam_ros.bags import convert_cli
    # The parser is built once (see the eval table): parse_args keeps no state.
    monkeypatch.setattr(convert_cli, 'build_parser', functools.lru_cache(
        convert_cli.build_parser))
    tried = 0
    for k, (name, text, truth) in enumerate(_convert_cases()):
        folder = tmp_path / f'c{k}'
        inp, gt = _write_run(folder, text, truth)
        out = folder / 'bag'
        argv = ['smartloc', '--input', inp, '--out', out, '--quiet']
        code, _, err = run(convert_main, argv + (['--truth', gt] if gt else []), capsys)
        assert_refused(code, err, 3, 'gnsscam_convert', gt if 'truth' in name or
                       name.startswith('point3') else inp)
        assert not out.exists() and not hidden_leftovers(folder), name
        tried += 1
    assert tried >= 100


def test_convert_output_refusals(tmp_path, capsys):
    src = ['smartloc', SMARTLOC_EXCERPT, '--quiet']
    existing = tmp_path / 'existing'
    existing.mkdir()
    (existing / 'keep.txt').write_text('mine')
    dangling = tmp_path / 'dangling'
    dangling.symlink_to(tmp_path / 'nowhere')
    a_file = tmp_path / 'a_file'
    a_file.write_text('x')
    before = snapshot(tmp_path)
    for out in (existing, dangling, a_file):
        code, _, err = run(convert_main, src + ['--out', out], capsys)
        assert_refused(code, err, 4, 'gnsscam_convert', out)
    js = tmp_path / 'summary.json'
    js.write_text('{}')
    code, _, err = run(convert_main, src + ['--out', tmp_path / 'new', '--json', js], capsys)
    assert_refused(code, err, 4, 'gnsscam_convert', js)
    assert js.read_text() == '{}' and not (tmp_path / 'new').exists()
    js.unlink()
    # A parent that is a file, a folder nobody may write in.
    for out in (a_file / 'bag', unwritable_folder(tmp_path) / 'bag'):
        code, _, err = run(convert_main, src + ['--out', out], capsys)
        assert_refused(code, err, 4, 'gnsscam_convert', out)
        assert not out.exists()
    assert snapshot(tmp_path / 'existing') == {k[len('existing/'):]: v
                                               for k, v in before.items()
                                               if k.startswith('existing/')}
    assert not hidden_leftovers(tmp_path)


# ============================================================ partial outputs (sweep)
def _partial(folder: Path, name: str) -> Path:
    path = folder / name
    path.mkdir()
    (path / 'bag').mkdir()
    (path / 'bag' / 'bag.mcap').write_bytes(b'\x89MCAP0\r\n' + b'\x00' * 1000)
    return path


def test_leftover_partials_removed_when_provably_stale_else_reported(tmp_path, capsys):
    host = partials._host()
    gone = dead_pid()
    stale = _partial(tmp_path, f'.bag.partial-{host}-{gone}-abc123')
    stale_other = _partial(tmp_path, f'.other.partial-{host}-{gone}-q1w2')
    live = _partial(tmp_path, f'.bag.partial-{host}-{os.getpid()}-live')
    remote = _partial(tmp_path, f'.bag.partial-elsewhere-{gone}-r3')
    legacy = _partial(tmp_path, '.bag.partial-k2j3h4l5')
    # pid 1 runs, but started long after this folder was last written: the pid was reused.
    reused = _partial(tmp_path, f'.bag.partial-{host}-1-old')
    boot = partials._boot_time_s()
    if boot is not None:
        for p in [reused, *reused.rglob('*')]:
            os.utime(p, (boot - 3600, boot - 3600))
    unrelated = tmp_path / '.hidden_config'
    unrelated.write_text('not ours')
    inp, _ = _write_run(tmp_path / 'in', GOOD_INPUT + 'junk\n')
    code, _, err = run(convert_main, ['smartloc', '--input', inp, '--out', tmp_path / 'bag',
                                      '--quiet'], capsys)
    assert code == 3 and 'Traceback' not in err
    assert not stale.exists() and not stale_other.exists()
    assert f'removed the leftover partial output {stale}' in err
    assert f'pid {gone}, no longer runs' in err
    for kept in (remote, legacy):
        assert kept.exists()
        assert f'leftover partial output {kept}' in err
        assert f"rm -rf -- {kept}" in err
    assert 'written on host elsewhere' in err
    # A running writer's partial output (here: this process's) is in use: left alone,
    # and not reported as a leftover.
    assert live.exists() and str(live) not in err
    if boot is not None:
        assert not reused.exists() and 'started after it was last written' in err
    assert unrelated.read_text() == 'not ours'
    # The error line is the last one and names the input file and line.
    assert err.strip().splitlines()[-1].startswith(f'gnsscam_convert: {inp}:3:')


def test_partial_names_carry_host_and_pid(tmp_path):
    made = partials.make_partial_dir(tmp_path / 'out')
    try:
        host = ''.join(c if c.isalnum() or c in '_.' else '_' for c in socket.gethostname())
        assert made.name.startswith(f'.out.partial-{host}-{os.getpid()}-')
        # Our own partial output is never taken for a leftover while we run.
        found = partials.sweep_partials(tmp_path)
        assert [(f.removed, f.in_use) for f in found] == [(False, True)] and made.exists()
    finally:
        shutil.rmtree(made)


def _file_writers(mapdb_set):
    """``{output name: write(path)}``: every writer of a whole file."""
    db = MapDatabase.load(mapdb_set[3])
    return {
        'r.json': lambda out: write_json_atomic(out, {'a': 1.5}, force=True),
        't.csv': lambda out: write_csv_atomic(out, ['a'], [[1.5]], force=True),
        'c.npz': lambda out: write_npz_atomic(out, a=np.arange(3)),
        'map.npz': lambda out: db.save(out, overwrite=True),
    }


def test_file_writers_name_their_temporary_file_as_partial_outputs(mapdb_set, tmp_path,
                                                                   monkeypatch):
    """While a JSON, CSV, npz or database file is written, its temporary file is
    ``.NAME.partial-HOST-PID-*``: what a SIGKILL leaves says whose it was."""
    seen = {}
    for name, write in _file_writers(mapdb_set).items():
        out = tmp_path / name
        real_replace = os.replace

        def replace(src, dst, *args, out=out, **kwargs):
            seen[out.name] = Path(src).name          # the moment before the rename
            return real_replace(src, dst, *args, **kwargs)
        monkeypatch.setattr(os, 'replace', replace)
        write(out)
        monkeypatch.undo()
        assert seen[name].startswith(partials.partial_prefix(out)), seen
        assert out.is_file() and not hidden_leftovers(tmp_path)


@pytest.mark.parametrize('umask', [0o022, 0o077, 0o002])
def test_outputs_have_the_modes_of_the_users_files(mapdb_set, tmp_path, umask):
    """A finished output has the permissions ``open`` and ``mkdir`` give under the
    process's umask, not those of a private temporary file (0600 / 0700): a result, a map
    database or a bag folder others may read when the user's files may be read."""
    previous = os.umask(umask)
    try:
        for name, write in _file_writers(mapdb_set).items():
            write(tmp_path / name)
            assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
        folder = partials.make_partial_dir(tmp_path / 'bag')
        assert folder.stat().st_mode & 0o777 == 0o777 & ~umask
        folder.rmdir()
    finally:
        os.umask(previous)


def test_killed_file_writers_leftovers_removed_by_the_next_write(mapdb_set, tmp_path,
                                                                 capsys):
    """A leftover of a killed write (a dead pid's ``.NAME.partial-*`` file) is removed by
    the next write of the same output, with one line; a running writer's is left alone and
    not reported, and another output's is not this write's business."""
    host, gone = partials._host(), dead_pid()
    live_writer = subprocess.Popen(['sleep', '600'])
    try:
        for name, write in _file_writers(mapdb_set).items():
            out = tmp_path / name
            dead = tmp_path / f'.{name}.partial-{host}-{gone}-k1ll3d'
            live = tmp_path / f'.{name}.partial-{host}-{live_writer.pid}-w0rk1n'
            other = tmp_path / f'.other_{name}.partial-{host}-{gone}-0th3r'
            for path in (dead, live, other):
                path.write_bytes(b'half a file')
            write(out)
            err = capsys.readouterr().err
            assert not dead.exists(), err
            assert (f'removed the leftover partial output {dead} (its writer, pid {gone}, '
                    'no longer runs)') in err
            assert live.read_bytes() == b'half a file' and str(live) not in err
            assert other.read_bytes() == b'half a file' and str(other) not in err
            assert out.is_file()
            # Reported, never touched: a writer on another host.
            remote = tmp_path / f'.{name}.partial-elsewhere-{gone}-r3m0t3'
            remote.write_bytes(b'half a file')
            write(out)
            err = capsys.readouterr().err
            assert remote.exists() and f'rm -rf -- {remote}' in err
            for path in (live, other, remote):
                path.unlink()
        assert not hidden_leftovers(tmp_path)
    finally:
        live_writer.kill()
        live_writer.wait()


@pytest.mark.slow
def test_sigkilled_convert_leftover_is_removed_by_the_next_run(tmp_path, capsys):
    out = tmp_path / 'bag'
    proc = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.bags.convert_cli', 'emulated',
                             '--seed', '1', '--duration-s', '60', '--out', str(out),
                             '--quiet', '--workers', '1'],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        def partial_with_data():
            return [p for p in tmp_path.iterdir() if p.name.startswith('.bag.partial-')
                    and any(f.is_file() and f.stat().st_size > 0 for f in p.rglob('*'))]
        wait_until(lambda: partial_with_data() or proc.poll() is not None, 120.0,
                   'the conversion writing its partial bag')
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    left = partial_with_data()
    assert left and not out.exists()            # what SIGKILL leaves: nothing cleans it
    code, _, err = run(convert_main, ['smartloc', SMARTLOC_EXCERPT, '--out', out, '--quiet'],
                       capsys)
    assert code == 0, err
    assert f'removed the leftover partial output {left[0]}' in err
    assert not left[0].exists() and out.is_dir()
    assert not hidden_leftovers(tmp_path)


# =================================================================== gnsscam_mapdb
GOOD_NAMES = ('good_a.png', 'good_b.png', 'good_c.png')
BUILD_OPTS = ['--branching', '6', '--depth', '3', '--nfeatures', '300', '--jobs', '1',
              '--quiet']


@pytest.fixture(scope='module')
def mapdb_set(tmp_path_factory):
    """Three good images, a CSV and a small database built from them."""
    root = tmp_path_factory.mktemp('mapdb')
    images = root / 'images'
    images.mkdir()
    for k, name in enumerate(GOOD_NAMES):
        cv2.imwrite(str(images / name), synthetic_scene(k))
    csv = root / 'positions.csv'
    csv.write_text('filename,east_m,north_m,up_m\n' + ''.join(
        f'{n},{10.0 * k},0,0\n' for k, n in enumerate(GOOD_NAMES)))
    db = root / 'db.npz'
    assert mapdb_cli.main(['build', '--images', str(images), '--positions', str(csv),
                           '--out', str(db)] + BUILD_OPTS) == 0
    return root, images, csv, db


@pytest.mark.slow
def test_mapdb_query_refuses_each_unusable_image(mapdb_set, tmp_path, capsys):
    _, images, _, db = mapdb_set
    reasons = image_cases(tmp_path)
    reasons[str(Path('/dev/zero'))] = 'not a regular file'
    reasons[str(tmp_path / 'absent.png')] = 'no such image file'
    good = images / GOOD_NAMES[0]
    for name, why in reasons.items():
        path = tmp_path / name
        code, out, err = run(mapdb_cli.main, ['query', '--db', db, path], capsys)
        line = assert_refused(code, err, 3, 'gnsscam_mapdb', path)
        assert why in line, (name, line)
    assert len(reasons) >= 39
    # Several at once: every bad one named, the good one answered, exit 3, the JSON says
    # which failed.
    js = tmp_path / 'answers.json'
    bad = [tmp_path / 'one_pixel.png', tmp_path / 'huge_dimensions.png',
           tmp_path / 'garbage_3.png']
    code, out, err = run(mapdb_cli.main, ['query', '--db', db, *bad, good, '--json', js],
                         capsys)
    assert code == 3 and 'Traceback' not in err
    assert [line.split(': ')[2] for line in err.strip().splitlines()] == [
        str(p) for p in bad]
    import json
    answers = json.loads(js.read_text())
    assert [bool(a.get('error')) for a in answers] == [True, True, True, False]
    assert answers[3]['matches'][0]['filename'] == GOOD_NAMES[0]


def test_mapdb_build_skips_unusable_rows_by_name(mapdb_set, tmp_path, capsys):
    _, images, _, _ = mapdb_set
    folder = tmp_path / 'images'
    folder.mkdir()
    reasons = image_cases(folder)
    for name in GOOD_NAMES:
        shutil.copy(images / name, folder / name)
    outside = tmp_path / 'outside.png'
    shutil.copy(images / GOOD_NAMES[0], outside)        # a usable image, but not inside
    (folder / 'link_out.png').symlink_to(outside)
    (folder / 'link_etc').symlink_to('/etc/hostname')
    (folder / 'sub').mkdir()
    traversal = {'/etc/hostname': 'outside the image folder',
                 '../outside.png': 'outside the image folder',
                 'sub/../../outside.png': 'outside the image folder',
                 str(outside): 'outside the image folder',
                 'link_out.png': 'outside the image folder',
                 'link_etc': 'outside the image folder',
                 '/dev/zero': 'outside the image folder',
                 'sub': 'not a regular file',
                 'absent.png': 'no such image file',
                 'nul\x00byte.png': 'NUL byte'}
    positions = {  # name -> (east, north, up); each row reuses a good image
        'pos_nan.png': ('nan', '0', '0'), 'pos_inf.png': ('inf', '0', '0'),
        'pos_1e300.png': ('1e300', '0', '0'), 'pos_neg.png': ('0', '-1e300', '0'),
        'pos_1e7.png': ('0', '0', '10000000.5'), 'pos_text.png': ('x', '0', '0'),
        'pos_empty.png': ('', '0', '0')}
    for name in positions:
        shutil.copy(images / GOOD_NAMES[1], folder / name)
    rows = ['filename,east_m,north_m,up_m']
    rows += [f'{n},{k},0,0' for k, n in enumerate(GOOD_NAMES)]
    rows += [f'{n},1,2,3' for n in list(reasons) + list(traversal)]
    rows += [f'{n},{e},{no},{u}' for n, (e, no, u) in positions.items()]
    rows += [f'{GOOD_NAMES[0]},5,5,5']                   # a duplicate row
    csv = tmp_path / 'positions.csv'
    csv.write_text('\n'.join(rows) + '\n')
    out = tmp_path / 'db.npz'
    code, _, err = run(mapdb_cli.main, ['build', '--images', folder, '--positions', csv,
                                        '--out', out] + BUILD_OPTS, capsys)
    assert code == 0 and 'Traceback' not in err, err
    skipped = [line for line in err.splitlines() if ': skipped ' in line]
    expected = {**reasons, **traversal, **{n: 'position' for n in positions}}
    assert len(skipped) == len(expected) + 1
    for name, why in expected.items():
        hit = [line for line in skipped if f'skipped {name} (line' in line]
        assert len(hit) == 1 and why in hit[0], (name, hit)
    assert len(MapDatabase.load(out)) == len(GOOD_NAMES)
    assert not hidden_leftovers(tmp_path)
    # Nothing usable at all: exit 3, the reasons, then one error naming the CSV.
    bad_only = tmp_path / 'bad_only.csv'
    bad_only.write_text('\n'.join([rows[0]] + rows[len(GOOD_NAMES) + 1:-1]) + '\n')
    out2 = tmp_path / 'none.npz'
    code, _, err = run(mapdb_cli.main, ['build', '--images', folder, '--positions',
                                        bad_only, '--out', out2] + BUILD_OPTS, capsys)
    assert code == 3 and 'Traceback' not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f'gnsscam_mapdb: error: {bad_only}: no usable image')
    assert not out2.exists() and not hidden_leftovers(tmp_path)


def test_mapdb_build_wgs84_positions_out_of_range(mapdb_set, tmp_path, capsys):
    _, images, _, _ = mapdb_set
    rows = ['filename,lat,lon,alt_m']
    cases = {'ok.png': '52.5,13.4,35', 'lat91.png': '91,13.4,35', 'lon181.png': '52.5,181,0',
             'latnan.png': 'nan,13.4,0', 'alt1e300.png': '52.5,13.4,1e300',
             'antipode.png': '-52.5,-166.6,0'}
    for name, value in cases.items():
        shutil.copy(images / GOOD_NAMES[2], tmp_path / name)
        rows.append(f'{name},{value}')
    (tmp_path / 'p.csv').write_text('\n'.join(rows) + '\n')
    code, _, err = run(mapdb_cli.main, ['build', '--images', tmp_path, '--positions',
                                        tmp_path / 'p.csv', '--out', tmp_path / 'w.npz']
                       + BUILD_OPTS, capsys)
    assert code == 0 and 'Traceback' not in err, err
    for name in set(cases) - {'ok.png'}:
        assert f'skipped {name} (line' in err, name
    assert 'from the origin' in err                       # the antipode, 12,700 km away
    db = MapDatabase.load(tmp_path / 'w.npz')
    assert db.filenames == ['ok.png']
    for origin in ('91,0', '0,181', 'nan,0', '0,0,1e300', 'x'):
        with pytest.raises(SystemExit) as info:
            mapdb_cli.main(['build', '--images', str(tmp_path), '--positions',
                            str(tmp_path / 'p.csv'), '--out', str(tmp_path / 'o.npz'),
                            '--origin', origin])
        assert info.value.code == 2
        assert 'Traceback' not in capsys.readouterr().err


def test_mapdb_bad_positions_csv(mapdb_set, tmp_path, capsys):
    _, images, _, _ = mapdb_set
    rng = np.random.default_rng(3)
    cases = {
        'empty.csv': b'', 'header_only.csv': b'filename,east_m,north_m\n',
        'no_filename.csv': b'name,east_m,north_m\na.png,1,2\n',
        'no_positions.csv': b'filename,x,y\na.png,1,2\n',
        'latin1.csv': 'filename,east_m,north_m\n\xe9.png,1,2\n'.encode('latin-1'),
        'huge_field.csv': b'filename,east_m,north_m\n"' + b'a' * 200_000 + b'",1,2\n',
        'binary.csv': rng.integers(0, 256, 4000, dtype=np.uint8).tobytes(),
        'nul.csv': b'filename,east_m,north_m\n\x00\x00\x00,1,2\n',
        'all_bad_rows.csv': b'filename,east_m,north_m\ngood_a.png,nan,0\ngood_b.png,1e300,0\n',
        # Faults further down, CRLF and bare CR line ends: the line is still the right one.
        'late_latin1.csv': b'filename,east_m,north_m\r\n' + b'a.png,1,2\r\n' * 3
        + 'b\xe9.png,1,2\r\n'.encode('latin-1'),
        'late_huge_field.csv': b'filename,east_m,north_m\r' + b'a.png,1,2\r' * 4
        + b'b.png,' + b'1' * 1_000_000 + b',2\r',
    }
    #: The line an error must name (``PATH:LINE``) where the fault has one.
    lines = {'no_filename.csv': 1, 'no_positions.csv': 1, 'latin1.csv': 2,
             'huge_field.csv': 2, 'late_latin1.csv': 5, 'late_huge_field.csv': 6}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    (tmp_path / 'a_folder.csv').mkdir()
    with open(tmp_path / 'sparse.csv', 'wb') as f:
        f.truncate(300 * 1024 * 1024)
    paths = [tmp_path / n for n in cases]
    paths += [tmp_path / 'a_folder.csv', tmp_path / 'sparse.csv', tmp_path / 'absent.csv',
              Path('/dev/zero')]
    for path in paths:
        out = tmp_path / 'x.npz'
        code, _, err = run(mapdb_cli.main, ['build', '--images', images, '--positions', path,
                                            '--out', out] + BUILD_OPTS, capsys)
        assert code == 3 and 'Traceback' not in err, (path, err)
        last = err.strip().splitlines()[-1]
        assert last.startswith('gnsscam_mapdb: error: ') and str(path) in last, (path, err)
        if path.name in lines:
            assert f'{path}:{lines[path.name]}: ' in last, (path, err)
        assert not out.exists() and not hidden_leftovers(tmp_path)
    code, _, err = run(mapdb_cli.main, ['build', '--images', tmp_path / 'nope', '--positions',
                                        paths[0], '--out', tmp_path / 'y.npz'], capsys)
    assert_refused(code, err, 3, 'gnsscam_mapdb', tmp_path / 'nope')


# ----------------------------------------------------------------- database files
def _arrays(db: Path) -> dict:
    with np.load(db) as z:
        return {k: z[k] for k in z.files}


def _npz(path: Path, arrays: dict) -> Path:
    with open(path, 'wb') as f:
        np.savez(f, **arrays)
    return path


def _patched_central_size(src: Path, dst: Path, member: str, size: int) -> Path:
    """A copy whose zip directory declares ``size`` bytes for ``member`` (a zip bomb's
    directory, without the gigabytes: the directory is what is checked)."""
    data = bytearray(src.read_bytes())
    at = data.find(b'PK\x01\x02')
    while at >= 0:
        name_len = int.from_bytes(data[at + 28:at + 30], 'little')
        name = bytes(data[at + 46:at + 46 + name_len]).decode()
        if name == member:
            data[at + 24:at + 28] = size.to_bytes(4, 'little')
        at = data.find(b'PK\x01\x02', at + 4)
    dst.write_bytes(bytes(data))
    return dst


def _npy_bomb(shape, dtype='<f4') -> bytes:
    """An .npy member that declares ``shape`` and holds 16 bytes."""
    header = {'descr': dtype, 'fortran_order': False, 'shape': shape}
    text = repr(header).encode('latin1')
    text += b' ' * (63 - (len(text) + 10) % 64) + b'\n'
    return b'\x93NUMPY\x01\x00' + len(text).to_bytes(2, 'little') + text + b'\x00' * 16


def database_cases(db: Path, folder: Path) -> dict[str, str]:
    """Write corrupt database files: ``{file name: expected message part}``."""
    good = db.read_bytes()
    a = _arrays(db)
    rng = np.random.default_rng(5)
    out: dict[str, str] = {}

    def raw(name, data, why):
        (folder / name).write_bytes(data)
        out[name] = why

    def variant(name, why, **changes):
        arrays = dict(a)
        for key, value in changes.items():
            if value is None:
                arrays.pop(key)
            else:
                arrays[key] = value
        _npz(folder / name, arrays)
        out[name] = why

    raw('empty.npz', b'', 'not a readable map database')
    for seed in range(10):
        raw(f'garbage_{seed}.npz', rng.integers(0, 256, 100 + 5000 * seed,
                                                dtype=np.uint8).tobytes(),
            'not a readable map database')
    raw('a_png.npz', cv2.imencode('.png', np.zeros((8, 8), np.uint8))[1].tobytes(),
        'not a readable map database')
    for cut in (4, 30, 100, 1000, len(good) // 2, len(good) - 30, len(good) - 1):
        raw(f'cut_{cut}.npz', good[:cut], 'not a readable map database')
    with zipfile.ZipFile(folder / 'empty_zip.npz', 'w'):
        pass
    out['empty_zip.npz'] = "no array 'format'"
    _patched_central_size(db, folder / 'dir_bomb.npz', 'inv_weights.npy', 0xFFFFFFF0)
    out['dir_bomb.npz'] = 'more than a map database may hold'
    with zipfile.ZipFile(db) as src, zipfile.ZipFile(folder / 'npy_bomb.npz', 'w') as dst:
        for info in src.infolist():
            data = (_npy_bomb((10 ** 12,)) if info.filename == 'inv_weights.npy'
                    else src.read(info))
            dst.writestr(info.filename, data)
    out['npy_bomb.npz'] = "array 'inv_weights' declares"
    with zipfile.ZipFile(db) as src, zipfile.ZipFile(folder / 'npy_bomb_2d.npz', 'w') as dst:
        for info in src.infolist():
            data = (_npy_bomb((10 ** 6, 10 ** 6), '<f8') if info.filename == 'pos_enu_m.npy'
                    else src.read(info))
            dst.writestr(info.filename, data)
    out['npy_bomb_2d.npz'] = "array 'pos_enu_m' declares"
    with open(folder / 'pickled.npz', 'wb') as f:
        np.savez(f, **{**a, 'meta': np.array([{'x': 1}], dtype=object)})
    out['pickled.npz'] = 'Python objects'
    n = len(a['filenames'])
    enu = a['pos_enu_m']
    variant('pos_1e300.npz', 'pos_enu_m', pos_enu_m=enu + np.array([1e300, 0, 0]))
    variant('pos_nan.npz', 'pos_enu_m', pos_enu_m=np.full_like(enu, np.nan))
    variant('pos_1e7.npz', 'pos_enu_m', pos_enu_m=enu + np.array([0, 0, 1.1e7]))
    variant('values_inf.npz', 'pos_values', pos_values=np.full_like(a['pos_values'], np.inf))
    variant('values_shape.npz', 'pos_values', pos_values=a['pos_values'][:, :1])
    variant('llh_lat100.npz', 'pos_llh', pos_llh=np.tile([100.0, 0.0, 0.0], (n, 1)))
    variant('origin_lat100.npz', 'pos_origin_llh', pos_origin_llh=np.array([100.0, 0, 0]))
    variant('image_index_n.npz', 'inv_images',
            inv_images=np.full_like(a['inv_images'], n))
    variant('image_index_neg.npz', 'inv_images',
            inv_images=np.full_like(a['inv_images'], -1))
    variant('indptr_down.npz', 'inv_indptr', inv_indptr=a['inv_indptr'][::-1].copy())
    variant('weights_nan.npz', 'inv_weights',
            inv_weights=np.full_like(a['inv_weights'], np.nan))
    variant('idf_negative.npz', 'inv_idf', inv_idf=-np.ones_like(a['inv_idf']))
    variant('branching_0.npz', 'branching', tree_branching=np.int64(0))
    variant('branching_1e6.npz', 'branching', tree_branching=np.int64(10 ** 6))
    variant('depth_100.npz', 'depth', tree_depth=np.int64(100))
    variant('centres_shape.npz', 'tree arrays', tree_centres=a['tree_centres'][:-1])
    variant('nfeatures_1e12.npz', 'nfeatures',
            orb_params=np.array('{"nfeatures": 1000000000000}'))
    variant('orb_list.npz', 'not a valid map database', orb_params=np.array('[]'))
    variant('orb_bogus.npz', 'bogus', orb_params=np.array('{"bogus": 1}'))
    variant('orb_not_json.npz', 'not a valid map database', orb_params=np.array('{{{'))
    variant('meta_nested.npz', 'RecursionError', meta=np.array('[' * 100_000 + ']' * 100_000))
    variant('format_other.npz', "format is 'something_else'",
            format=np.array('something_else'))
    variant('version_2.npz', 'format version 2', version=np.int64(2))
    variant('version_inf.npz', 'OverflowError', version=np.float64(np.inf))
    variant('no_idf.npz', "no array 'inv_idf'", inv_idf=None)
    variant('names_short.npz', 'file names', filenames=a['filenames'][:-1])
    variant('features_negative.npz', 'n_features',
            n_features=-np.ones_like(a['n_features']))
    variant('score_levels_0.npz', 'score_levels', score_levels=np.int64(0))
    variant('score_levels_99.npz', 'score_levels', score_levels=np.int64(99))
    variant('n_images_0.npz', 'not a valid map database', inv_n_images=np.int64(0))
    (folder / 'a_folder.npz').mkdir()
    out['a_folder.npz'] = 'not a regular file'
    out['absent.npz'] = 'no such database file'
    return out


def test_mapdb_refuses_corrupt_databases_before_allocating(mapdb_set, tmp_path, capsys):
    _, images, _, db = mapdb_set
    cases = database_cases(db, tmp_path)
    query = images / GOOD_NAMES[0]
    import resource
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for name, why in cases.items():
        path = tmp_path / name
        code, out, err = run(mapdb_cli.main, ['query', '--db', path, query], capsys)
        line = assert_refused(code, err, 3, 'gnsscam_mapdb', path)
        assert why in line, (name, line)
        assert out == ''
    # The bombs declare terabytes; peak memory grew by far less than one of them.
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before) / 1024
    assert grown_mb < 500
    assert len(cases) >= 55
    # A compressed database of valid arrays is still a database.
    with open(tmp_path / 'compressed.npz', 'wb') as f:
        np.savez_compressed(f, **_arrays(db))
    code, out, err = run(mapdb_cli.main, ['query', '--db', tmp_path / 'compressed.npz',
                                          query], capsys)
    assert code == 0 and GOOD_NAMES[0] in out, err


def test_mapdb_outputs_never_overwritten_nor_left_half_written(mapdb_set, tmp_path, capsys):
    _, images, csv, db = mapdb_set
    query = images / GOOD_NAMES[0]
    js = tmp_path / 'q.json'
    js.write_text('mine\n')
    code, _, err = run(mapdb_cli.main, ['query', '--db', db, query, '--json', js], capsys)
    assert_refused(code, err, 4, 'gnsscam_mapdb', js, 'already exists')
    assert js.read_text() == 'mine\n'
    code, out, err = run(mapdb_cli.main, ['query', '--db', db, query, '--json', js,
                                          '--force'], capsys)
    assert code == 0 and js.read_text().startswith('[')
    nowhere = unwritable_folder(tmp_path)
    for target in (tmp_path / 'missing' / 'q.json', tmp_path, nowhere / 'q.json'):
        code, _, err = run(mapdb_cli.main, ['query', '--db', db, query, '--json', target,
                                            '--force'], capsys)
        assert_refused(code, err, 4, 'gnsscam_mapdb', target)
    # build --out: existing (kept), a folder, a missing folder, a folder nobody may write.
    out_db = tmp_path / 'out.npz'
    out_db.write_bytes(b'keep')
    build = ['build', '--images', images, '--positions', csv] + BUILD_OPTS
    code, _, err = run(mapdb_cli.main, build + ['--out', out_db], capsys)
    assert_refused(code, err, 4, 'gnsscam_mapdb', out_db, 'already exists')
    assert out_db.read_bytes() == b'keep'
    for target in (tmp_path, tmp_path / 'missing' / 'db.npz', nowhere / 'db.npz'):
        code, _, err = run(mapdb_cli.main, build + ['--out', target, '--force'], capsys)
        assert_refused(code, err, 4, 'gnsscam_mapdb', target)
    assert not hidden_leftovers(tmp_path)
    # Settings a build would refuse only after every image: refused at once (usage).
    for extra in (['--branching', '1'], ['--depth', '12'], ['--score-levels', '4'],
                  ['--nfeatures', '10000000']):
        code, _, err = run(mapdb_cli.main, build + ['--out', tmp_path / 'n.npz'] + extra,
                           capsys)
        assert_refused(code, err, 2, 'gnsscam_mapdb')


@pytest.mark.slow
def test_mapdb_real_oversized_image_is_refused(tmp_path, capsys, mapdb_set):
    """A genuine 8100 x 8000 PNG (not a forged header): refused from its header."""
    _, _, _, db = mapdb_set
    big = tmp_path / 'big.png'
    cv2.imwrite(str(big), np.zeros((8000, 8100), np.uint8))
    code, _, err = run(mapdb_cli.main, ['query', '--db', db, big], capsys)
    line = assert_refused(code, err, 3, 'gnsscam_mapdb', big)
    assert 'larger than 64 Mpx' in line and 'declared in its header' in line
