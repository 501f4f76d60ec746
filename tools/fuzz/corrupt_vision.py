"""Corrupt images, positions CSVs and map databases for ``gnsscam_mapdb build`` and
``query``, and output paths for ``gnsscam_record``.

Documented: ``gnsscam_mapdb`` exits 0 on success, 3 on unusable input and 4 on an output it
cannot or must not write (messages naming the file), 2 on bad usage; a build skips (and
names) rows whose image is missing, unreadable or featureless; it never overwrites without
``--force``. The issue adds: skip unusable images by name, bound what is loaded, refuse
positions out of range and paths outside ``--images``, never overwrite (``query --json``
included). ``gnsscam_record``: 4 when the output exists or cannot be written, 2 bad usage;
leftovers of a killed run are removed or reported on the next run.
"""
from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np

from gnsscam_ros.vision.database import MapDatabase

from . import corrupt_inputs
from .corpus import Corpus
from .corrupt_inputs import IMAGE_FAULTS, unwritable_folder
from .filecase import FileCase, all_removed, killed_writer_leftovers, named

IMAGE_VARIANTS = tuple(IMAGE_FAULTS)
#: Images a correct tool uses (or answers without a match): not an error.
IMAGE_BENIGN = ('png_named_jpg',)


def write_image(kind: str, rng, good: Path, path: Path) -> None:
    """A corrupt image of ``kind`` at ``path`` (from the valid image file ``good``)."""
    corrupt_inputs.write_image(kind, rng, good.read_bytes(), path)


def _image_set(corpus: Corpus, folder: Path) -> tuple[Path, Path, list[str]]:
    images = folder / 'images'
    shutil.copytree(corpus.images, images)
    csv = folder / 'positions.csv'
    shutil.copy(corpus.positions, csv)
    return images, csv, sorted(p.name for p in images.iterdir())


def _finite_database(bound_m: float = 1e7):
    def check(outcome, out: Path) -> str | None:
        if not out.exists():
            return None
        db = MapDatabase.load(out)
        enu = db.positions.enu_m
        if not np.all(np.isfinite(enu)) or np.abs(enu).max(initial=0.0) > bound_m:
            return f'database holds positions beyond {bound_m:g} m'
        outside = [f for f in db.filenames if f.startswith(('/', '..'))]
        if outside:
            return f'database holds images outside --images: {outside}'
        return None
    return check


CSV_VARIANTS = ('position_nan', 'position_1e300', 'latitude_1e300', 'outside_relative',
                'outside_absolute', 'no_header', 'empty', 'binary', 'no_position_columns',
                'missing', 'all_rows_bad', 'duplicate_rows', 'field_1mb', 'bom')
CSV_BENIGN = ('duplicate_rows', 'bom', 'position_nan')
BUILD_OUTPUT_VARIANTS = ('out_existing', 'out_unwritable', 'out_is_folder', 'images_missing',
                         'stale_partials')


def mapdb_build_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    images, csv, names = _image_set(corpus, folder)
    out = folder / 'map.npz'
    opts = ['--branching', '8', '--depth', '2', '--nfeatures', '300', '--jobs', '1',
            '--quiet']
    protect, watch = [csv], [folder]
    argv = ['--images', str(images), '--positions', str(csv), '--out', str(out), *opts]
    checker = _finite_database()
    group = i % 3
    if group == 0:                          # one corrupt image among good ones
        kind = IMAGE_VARIANTS[(i // 3) % len(IMAGE_VARIANTS)]
        victim = images / names[int(rng.integers(len(names)))]
        victim.unlink()
        write_image(kind, rng, corpus.images / victim.name, victim)
        expect = (0,)
        return FileCase('mapdb_build', f'image_{kind}', argv, expect,
                        names=[] if kind in IMAGE_BENIGN else named(victim),
                        protect=protect, watch=watch, allowed=[out],
                        check=lambda o: checker(o, out))
    if group == 1:
        kind = CSV_VARIANTS[(i // 3) % len(CSV_VARIANTS)]
        line = _corrupt_csv(kind, rng, csv, folder)
        expect = (0,) if kind in CSV_BENIGN else (0, 3) if kind in (
            'position_1e300', 'latitude_1e300', 'outside_relative', 'outside_absolute') \
            else (3,)
        return FileCase('mapdb_build', f'csv_{kind}', argv, expect,
                        names=[] if kind in CSV_BENIGN else named(csv), line=line,
                        protect=[] if kind == 'missing' else protect, watch=watch,
                        allowed=[out], check=lambda o: checker(o, out))
    kind = BUILD_OUTPUT_VARIANTS[(i // 3) % len(BUILD_OUTPUT_VARIANTS)]
    if kind == 'stale_partials':            # a killed earlier build left its temporary file
        stale = killed_writer_leftovers(rng, out)
        return FileCase('mapdb_build', f'output_{kind}', argv, (0,), protect=protect,
                        watch=watch, allowed=[out], stale=stale,
                        check=all_removed(stale, lambda o: checker(o, out)))
    if kind == 'out_existing':
        out.write_bytes(corpus.database.read_bytes())
        protect.append(out)
    elif kind == 'out_unwritable':
        out = unwritable_folder(folder) / 'map.npz'
    elif kind == 'out_is_folder':
        out.mkdir()
    else:
        shutil.rmtree(images)
    argv = ['--images', str(images), '--positions', str(csv), '--out', str(out), *opts]
    return FileCase('mapdb_build', f'output_{kind}', argv,
                    (3,) if kind == 'images_missing' else (4,),
                    names=named(images if kind == 'images_missing' else out),
                    protect=protect, watch=watch)


def _corrupt_csv(kind: str, rng, csv: Path, folder: Path) -> int | None:
    """Corrupt the positions CSV in place; the line a refusal should name (or None)."""
    lines = csv.read_text().splitlines()
    k = int(rng.integers(1, len(lines)))
    cells = lines[k].split(',')
    line = k + 1
    if kind == 'position_nan':
        cells[1] = 'nan'
    elif kind == 'position_1e300':
        cells[int(rng.integers(1, 4))] = '1e300'
    elif kind == 'latitude_1e300':
        lines[0] = 'filename,lat,lon,alt_m'
        for j in range(1, len(lines)):
            c = lines[j].split(',')
            lines[j] = f'{c[0]},50.1,8.68,100'
        cells = lines[k].split(',')
        cells[1] = '1e300'
    elif kind == 'outside_relative':
        outside = folder / 'outside.jpg'
        shutil.copy(folder / 'images' / cells[0], outside)
        cells[0] = '../outside.jpg'
    elif kind == 'outside_absolute':
        cells[0] = '/etc/hostname'
    elif kind == 'duplicate_rows':
        lines.insert(k, lines[k])
    lines[k] = ','.join(cells)
    if kind == 'no_header':
        lines = lines[1:]
        line = None
    elif kind == 'no_position_columns':
        lines = ['filename,x,y'] + lines[1:]
        line = 1
    elif kind == 'all_rows_bad':
        lines = [lines[0]] + [f'{c.split(",")[0]},nan,nan,nan' for c in lines[1:]]
        line = None
    elif kind == 'field_1mb':
        lines[k] = cells[0] + ',' + '1' * 1_000_000 + ',0,0'
    text = '\n'.join(lines) + '\n'
    if kind == 'empty':
        text, line = '', None
    if kind == 'bom':
        text = '\ufeff' + text
    if kind == 'binary':
        csv.write_bytes(rng.bytes(int(rng.integers(10, 5000))))
        return None
    if kind == 'missing':
        csv.unlink()
        return None
    csv.write_text(text, encoding='utf-8')
    return line if kind not in ('duplicate_rows', 'bom') else None


DB_VARIANTS = ('truncated', 'bytes_flipped', 'garbage', 'empty', 'missing', 'folder',
               'key_missing', 'object_array', 'positions_nan', 'positions_1e300',
               'lengths_inconsistent', 'tree_out_of_range', 'header_bomb', 'text')
QUERY_OUTPUT_VARIANTS = ('json_existing', 'json_unwritable', 'json_is_folder',
                         'json_stale_partials')


def write_database(kind: str, rng, good: Path, path: Path) -> None:
    """A corrupt map database of ``kind`` at ``path``."""
    data = good.read_bytes()
    if kind == 'truncated':
        path.write_bytes(data[:int(len(data) * rng.uniform(0.01, 0.99))])
        return
    if kind == 'bytes_flipped':
        raw = bytearray(data)
        for j in rng.integers(0, len(raw), int(rng.integers(1, 32))):
            raw[int(j)] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(raw))
        return
    if kind in ('garbage', 'empty', 'text', 'folder', 'missing'):
        if kind == 'garbage':
            path.write_bytes(rng.bytes(len(data)))
        elif kind == 'empty':
            path.write_bytes(b'')
        elif kind == 'text':
            path.write_text('not a database\n')
        elif kind == 'folder':
            path.mkdir()
        return
    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    if kind == 'header_bomb':
        _header_bomb(arrays, path)
        return
    if kind == 'key_missing':
        del arrays[list(arrays)[int(rng.integers(len(arrays)))]]
    elif kind == 'object_array':
        arrays['filenames'] = np.array([object(), 'x'], dtype=object)
    elif kind == 'positions_nan':
        arrays['pos_enu_m'] = arrays['pos_enu_m'] * np.nan
    elif kind == 'positions_1e300':
        arrays['pos_enu_m'] = arrays['pos_enu_m'] + 1e300
        arrays['pos_values'] = arrays['pos_values'] + 1e300
    elif kind == 'lengths_inconsistent':
        arrays['filenames'] = arrays['filenames'][:1]
    elif kind == 'tree_out_of_range':
        arrays['inv_indptr'] = arrays['inv_indptr'] + 10**9
    with path.open('wb') as f:
        np.savez(f, **arrays, allow_pickle=True) if kind == 'object_array' else \
            np.savez(f, **arrays)


def _header_bomb(arrays: dict, path: Path) -> None:
    """An npz whose ``pos_enu_m`` claims 8 TB (a loader that trusts it allocates that)."""
    with zipfile.ZipFile(path, 'w') as zf:
        for key, value in arrays.items():
            with zf.open(f'{key}.npy', 'w') as f:
                if key == 'pos_enu_m':
                    np.lib.format.write_array_header_1_0(
                        f, {'descr': '<f8', 'fortran_order': False,
                            'shape': (10**6, 10**6)})
                    f.write(b'\x00' * 64)
                else:
                    np.lib.format.write_array(f, value)


def mapdb_query_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    db = folder / 'map.npz'
    query = folder / 'query.jpg'
    shutil.copy(corpus.images / 'img_000.jpg', query)
    group = i % 3
    if group in (0, 1) and not (i % 10 == 9):
        if group == 0:
            kind = DB_VARIANTS[(i // 3) % len(DB_VARIANTS)]
            write_database(kind, rng, corpus.database, db)
            return FileCase('mapdb_query', f'database_{kind}',
                            ['--db', str(db), str(query)], (3,), names=named(db),
                            watch=[folder])
        shutil.copy(corpus.database, db)
        kind = IMAGE_VARIANTS[(i // 3) % len(IMAGE_VARIANTS)]
        query.unlink()
        write_image(kind, rng, corpus.images / 'img_000.jpg', query)
        benign = kind in IMAGE_BENIGN or kind in ('grey_featureless', 'one_pixel',
                                                  'two_by_two')
        return FileCase('mapdb_query', f'image_{kind}', ['--db', str(db), str(query)],
                        (0,) if kind in IMAGE_BENIGN else (0, 3) if benign else (3,),
                        names=[] if kind in IMAGE_BENIGN else named(query), watch=[folder])
    shutil.copy(corpus.database, db)
    kind = QUERY_OUTPUT_VARIANTS[i % len(QUERY_OUTPUT_VARIANTS)]
    out = folder / 'matches.json'
    protect = [db, query]
    if kind == 'json_existing':
        out.write_text('{"keep": true}\n')
        protect.append(out)
    elif kind == 'json_unwritable':
        out = unwritable_folder(folder) / 'matches.json'
    elif kind == 'json_stale_partials':     # a killed earlier query left its temporary file
        stale = killed_writer_leftovers(rng, out)
        return FileCase('mapdb_query', f'output_{kind}',
                        ['--db', str(db), str(query), '--json', str(out)], (0,),
                        protect=protect, watch=[folder], allowed=[out], stale=stale,
                        check=all_removed(stale))
    else:
        out.mkdir()
    return FileCase('mapdb_query', f'output_{kind}',
                    ['--db', str(db), str(query), '--json', str(out)], (4,),
                    names=named(out), protect=protect, watch=[folder])


# ====================================================================== record
RECORD_VARIANTS = ('existing_folder', 'existing_file', 'unwritable', 'through_file',
                   'read_only_folder', 'name_too_long', 'parent_missing', 'stale_partials',
                   'empty_name', 'existing_sqlite3')


def record_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    kind = RECORD_VARIANTS[i % len(RECORD_VARIANTS)]
    name = f'result_{rng.integers(1 << 30):x}'
    out = folder / name
    protect, stale, expect, allowed, locked = [], [], (4,), [], []
    extra = ['--duration', '0.3']
    if kind in ('existing_folder', 'existing_sqlite3'):
        out.mkdir()
        (out / 'keep.txt').write_text('keep\n')
        protect.append(out / 'keep.txt')
        if kind == 'existing_sqlite3':
            extra += ['--storage', 'sqlite3']
    elif kind == 'existing_file':
        out.write_text('keep\n')
        protect.append(out)
    elif kind == 'unwritable':
        out = unwritable_folder(folder) / name
    elif kind == 'through_file':
        blocker = folder / 'a_file'
        blocker.write_text('keep\n')
        protect.append(blocker)
        out = blocker / name
    elif kind == 'read_only_folder':
        ro = folder / 'read_only'
        ro.mkdir()
        out = ro / name
        locked = [ro]
    elif kind == 'name_too_long':
        out = folder / ('r' * int(rng.integers(256, 400)))
    elif kind == 'parent_missing':
        out = folder / 'a' / 'b' / name
        expect, allowed = (0, 4), [folder / 'a']
    elif kind == 'stale_partials':
        for _ in range(int(rng.integers(1, 4))):
            p = folder / f'.{name}.partial-{rng.integers(1 << 30):x}'
            p.mkdir()
            (p / 'junk.mcap').write_bytes(rng.bytes(4096))
            stale.append(p)
        expect, allowed = (0,), [out]
    elif kind == 'empty_name':
        out = Path('')
        expect = (2, 4)
    return FileCase('record', f'out_{kind}', ['--out', str(out), *extra], expect,
                    names=named(out) if str(out) not in ('', '.') else [],
                    protect=protect, watch=[folder], allowed=allowed, stale=stale,
                    read_only=locked)
