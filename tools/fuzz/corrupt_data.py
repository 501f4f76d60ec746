"""Corrupt bags and libRSF text, and the cases of the tools that read them:
``gnsscam_replay`` and ``gnsscam_eval bag`` (bags), ``gnsscam_eval smartloc`` and
``gnsscam_convert smartloc`` (libRSF text; their outputs too).

Documented exit codes: ``gnsscam_replay`` 3 for a missing, unreadable or wrong bag (README:
"a missing, truncated or corrupt bag, an unknown message type, a topic with the wrong
type ... one clear error naming the file ... exit code 3"); ``gnsscam_eval`` 3 bad input, 4
an output refused; ``gnsscam_convert`` 3 bad input, 4 output refused or failed. The issue
adds: libRSF lines with non-finite or absurd values are refused with file and line.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from gnsscam_ros.bags.read import bag_topics

from .corpus import Corpus
from .corrupt_inputs import BAD_NUMBERS, FIELD_FAULTS, FILE_FAULTS, file_fault, unwritable_folder
from .filecase import FileCase, named

BAG_VARIANTS = ('truncated', 'bytes_flipped', 'garbage', 'empty_storage', 'storage_missing',
                'metadata_garbage', 'metadata_truncated', 'metadata_empty', 'empty_folder',
                'missing', 'text_file', 'wrong_type', 'metadata_unknown_storage',
                'sqlite_garbage', 'mcap_named_db3', 'junk_appended', 'symlink_loop')
#: Variants that are valid bags, played in full (exit 0). ``mcap_named_db3``: the storage
#: file renamed ``.db3`` in the folder and in ``metadata.yaml``, whose
#: ``storage_identifier`` still says ``mcap``; rosbag2 (and rosbags) pick the storage plugin
#: from that field, not from the file's suffix, so the bag reads as the original does (a
#: bare MCAP file named ``.db3``, without metadata, is opened as SQLite and refused).
BAG_VALID = ('mcap_named_db3',)


def _storage_file(bag: Path) -> Path:
    return next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))


def make_bag(kind: str, rng: np.random.Generator, corpus: Corpus, folder: Path
             ) -> tuple[Path, str, bool]:
    """A corrupt bag of ``kind`` under ``folder``: ``(path, label, may_play)``; ``may_play``:
    a reader cannot always tell (a flipped byte inside a payload), so exit 0 is fine."""
    bag = folder / 'bag'
    if kind == 'missing':
        return bag, kind, False
    if kind == 'empty_folder':
        bag.mkdir()
        return bag, kind, False
    if kind == 'text_file':
        bag.write_text('not a bag\n')
        return bag, kind, False
    if kind == 'symlink_loop':
        os.symlink(bag, bag)
        return bag, kind, False
    shutil.copytree(corpus.wrong_type_bag if kind == 'wrong_type' else corpus.bag, bag)
    store = _storage_file(bag)
    data = store.read_bytes()
    meta = bag / 'metadata.yaml'
    label, may_play = kind, False
    if kind == 'truncated':
        frac = float(rng.uniform(0.02, 0.98))
        store.write_bytes(data[:int(len(data) * frac)])
        label = f'truncated_{frac:.0%}'
    elif kind == 'bytes_flipped':
        raw = bytearray(data)
        n = int(rng.integers(1, 64))
        for i in rng.integers(0, len(raw), n):
            raw[int(i)] ^= 1 << int(rng.integers(8))
        store.write_bytes(bytes(raw))
        label, may_play = f'bytes_flipped_{n}', True
    elif kind == 'garbage':
        store.write_bytes(rng.bytes(len(data)))
    elif kind == 'empty_storage':
        store.write_bytes(b'')
    elif kind == 'storage_missing':
        store.unlink()
    elif kind == 'metadata_garbage':
        meta.write_bytes(rng.bytes(int(rng.integers(1, 4096))))
    elif kind == 'metadata_truncated':
        text = meta.read_bytes()
        meta.write_bytes(text[:int(rng.integers(1, len(text)))])
    elif kind == 'metadata_empty':
        meta.write_bytes(b'')
    elif kind == 'metadata_unknown_storage':
        meta.write_text(meta.read_text().replace('storage_identifier: mcap',
                                                 'storage_identifier: tape'))
    elif kind == 'sqlite_garbage':
        store.rename(store.with_suffix('.db3'))
        store.with_suffix('.db3').write_bytes(b'SQLite format 3\x00' + rng.bytes(4096))
        meta.write_text(meta.read_text().replace('storage_identifier: mcap',
                                                 'storage_identifier: sqlite3')
                        .replace(store.name, store.with_suffix('.db3').name))
    elif kind == 'mcap_named_db3':
        store.rename(store.with_suffix('.db3'))
        meta.write_text(meta.read_text().replace(store.name, store.with_suffix('.db3').name))
    elif kind == 'junk_appended':
        store.write_bytes(data + rng.bytes(int(rng.integers(1, 100_000))))
        may_play = True
    return bag, label, may_play


def replay_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    kind = BAG_VARIANTS[i % len(BAG_VARIANTS)]
    bag, label, may_play = make_bag(kind, rng, corpus, folder)
    argv = [str(bag), '--rate', '0', '--wait', '0.2', '--ack-timeout', '2',
            '--no-dds-profile']
    if kind in BAG_VALID:
        summary = folder / 'replay.json'
        return FileCase('replay', f'bag_{label}', argv + ['--json', str(summary)], (0,),
                        names=named(bag, bag / 'metadata.yaml'), watch=[folder],
                        allowed=[summary], check=_plays_like(corpus.bag, summary))
    return FileCase('replay', f'bag_{label}', argv,
                    (0, 3) if may_play else (3,), names=named(bag, bag / 'metadata.yaml'),
                    watch=[folder])


def _plays_like(original: Path, summary: Path):
    """``check(outcome)``: the replay published every message of ``original``, per topic."""
    def check(_outcome) -> str | None:
        played = json.loads(summary.read_text(encoding='utf-8'))['published']
        held = {topic: n for topic, (_, n) in bag_topics(original).items()}
        if played != held:
            return f'published {played}, the original bag holds {held}'
        return None
    return check


def eval_bag_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    # Exit 3 for the valid variants too: the corpus bag is a dataset bag, without the
    # nodes' outputs that gnsscam_eval bag evaluates.
    kind = BAG_VARIANTS[(i * 7 + 3) % len(BAG_VARIANTS)]
    bag, label, _ = make_bag(kind, rng, corpus, folder)
    out = folder / 'metrics.json'
    return FileCase('eval_bag', f'bag_{label}', [str(bag), '--quiet', '--json', str(out)],
                    (3,), names=named(bag, bag / 'metadata.yaml'), watch=[folder])


# ====================================================================== libRSF text
#: A bad number in a random field of a random line (``value_nan``, ...).
VALUE_VARIANTS = {f'value_{v}': v for v in BAD_NUMBERS}
LIBRSF_VARIANTS = (
    *VALUE_VARIANTS, *FIELD_FAULTS, *FILE_FAULTS, 'field_dropped', 'field_added',
    'unknown_tag', 'cut_mid_line', 'missing', 'directory', 'time_backwards', 'truth_nan',
    'truth_garbage', 'token_1mb', 'duplicate_satellite')
#: Variants a correct loader accepts (exit 0).
LIBRSF_BENIGN = (*(k for k, why in FILE_FAULTS.items() if why is None),
                 'duplicate_satellite')


def _data_lines(text: str, tag: str | None = None) -> list[int]:
    return [i for i, line in enumerate(text.split('\n'))
            if line.split() and (tag is None or line.split()[0] == tag)]


def _set_field(text: str, rng, value: str, tag: str | None = None, field: int | None = None
               ) -> tuple[str, int]:
    """``text`` with one field of a random data line set to ``value``; (text, line no)."""
    lines = text.split('\n')
    idx = _data_lines(text, tag)
    k = idx[int(rng.integers(len(idx)))]
    tokens = lines[k].split()
    j = field if field is not None else int(rng.integers(1, len(tokens)))
    tokens[j] = value
    lines[k] = ' '.join(tokens)
    return '\n'.join(lines), k + 1


def make_librsf(kind: str, rng, corpus: Corpus, folder: Path
                ) -> tuple[Path, Path, int | None, Path]:
    """Corrupt copies of the input and truth files: ``(input, truth, line, bad file)``."""
    inp, truth = folder / 'run_Input.txt', folder / 'run_GT.txt'
    text = corpus.librsf_input.read_text()
    shutil.copy(corpus.librsf_truth, truth)
    line, bad = None, inp
    if kind in VALUE_VARIANTS:
        text, line = _set_field(text, rng, VALUE_VARIANTS[kind])
    elif kind in FIELD_FAULTS:
        tag, field, value, _ = FIELD_FAULTS[kind]
        text, line = _set_field(text, rng, value, tag, field)
    elif kind == 'token_1mb':
        text, line = _set_field(text, rng, '1' * 1_000_000)
    elif kind in ('field_dropped', 'field_added', 'unknown_tag', 'time_backwards',
                  'duplicate_satellite'):
        text, line = _line_fault(kind, text, rng)
    elif kind == 'cut_mid_line':
        lines = text.rstrip('\n').split('\n')
        last = lines[-1].split()
        lines[-1] = ' '.join(last[:int(rng.integers(1, len(last)))])
        text, line = '\n'.join(lines), len(lines)
    elif kind in ('truth_nan', 'truth_garbage'):
        bad = truth
        if kind == 'truth_nan':
            ttext, line = _set_field(truth.read_text(), rng, 'nan')
            truth.write_text(ttext)
        else:
            truth.write_bytes(rng.bytes(int(rng.integers(10, 5000))))
    inp_bytes = file_fault(kind, text.encode(), rng) if kind in FILE_FAULTS else text.encode()
    if kind == 'missing':
        pass
    elif kind == 'directory':
        inp.mkdir()
    else:
        inp.write_bytes(inp_bytes)
    return inp, truth, line, bad


def _line_fault(kind: str, text: str, rng) -> tuple[str, int]:
    lines = text.split('\n')
    idx = _data_lines(text)
    k = idx[int(rng.integers(len(idx)))]
    tokens = lines[k].split()
    if kind == 'field_dropped':
        del tokens[int(rng.integers(1, len(tokens)))]
    elif kind == 'field_added':
        tokens.insert(int(rng.integers(1, len(tokens) + 1)), '0')
    elif kind == 'unknown_tag':
        tokens[0] = 'range9'
    elif kind == 'duplicate_satellite':
        k = _data_lines(text, 'pseudorange3')[int(rng.integers(10))]
        lines.insert(k + 1, lines[k])
        return '\n'.join(lines), k + 2
    else:                                   # time_backwards: an epoch before the first
        k = _data_lines(text, 'pseudorange3')[-1]
        tokens = lines[k].split()
        tokens[1] = '-5'
    lines[k] = ' '.join(tokens)
    return '\n'.join(lines), k + 1


def _librsf(i: int, rng, corpus: Corpus, folder: Path):
    kind = LIBRSF_VARIANTS[i % len(LIBRSF_VARIANTS)]
    inp, truth, line, bad = make_librsf(kind, rng, corpus, folder)
    benign = kind in LIBRSF_BENIGN
    return kind, inp, truth, line, bad, benign


EVAL_OUTPUT_VARIANTS = ('json_existing', 'json_unwritable', 'json_is_folder',
                        'epochs_csv_existing')


def eval_smartloc_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    filt = ['--particles', '100', '--posteriors', '10', '--quiet']
    out = folder / 'metrics.json'
    if i % 10 == 9:                          # an output that must be refused
        kind = EVAL_OUTPUT_VARIANTS[(i // 10) % len(EVAL_OUTPUT_VARIANTS)]
        inp, truth = folder / 'run_Input.txt', folder / 'run_GT.txt'
        shutil.copy(corpus.librsf_input, inp)
        shutil.copy(corpus.librsf_truth, truth)
        protect, argv_out = [inp, truth], ['--json', str(out)]
        if kind == 'json_existing':
            out.write_text('{"keep": true}\n')
            protect.append(out)
        elif kind == 'json_unwritable':
            out = unwritable_folder(folder) / 'metrics.json'
            argv_out = ['--json', str(out)]
        elif kind == 'json_is_folder':
            out.mkdir()
        else:
            csv = folder / 'epochs.csv'
            csv.write_text('keep\n')
            protect.append(csv)
            argv_out = ['--epochs-csv', str(csv)]
            out = csv
        return FileCase('eval_smartloc', f'output_{kind}',
                        ['--input', str(inp), '--truth', str(truth), *filt, *argv_out], (4,),
                        names=named(out), protect=protect, watch=[folder])
    kind, inp, truth, line, bad, benign = _librsf(i, rng, corpus, folder)
    return FileCase('eval_smartloc', f'librsf_{kind}',
                    ['--input', str(inp), '--truth', str(truth), *filt, '--json', str(out)],
                    (0,) if benign else (3,), names=named(bad), line=line,
                    watch=[folder], allowed=[out])


CONVERT_OUTPUT_VARIANTS = ('out_existing_folder', 'out_existing_file', 'out_unwritable',
                           'out_through_file', 'json_existing', 'stale_partials')


def convert_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    if i % 5 == 4:
        return _convert_output_case(i, rng, corpus, folder)
    kind, inp, truth, line, bad, benign = _librsf(i * 3 + 1, rng, corpus, folder)
    out = folder / 'out_bag'
    return FileCase('convert', f'librsf_{kind}',
                    ['--input', str(inp), '--truth', str(truth), '--out', str(out), '--quiet'],
                    (0,) if benign else (3,), names=named(bad), line=line, watch=[folder],
                    allowed=[out])


def _convert_output_case(i: int, rng, corpus: Corpus, folder: Path) -> FileCase:
    kind = CONVERT_OUTPUT_VARIANTS[(i // 5) % len(CONVERT_OUTPUT_VARIANTS)]
    inp, truth = folder / 'run_Input.txt', folder / 'run_GT.txt'
    shutil.copy(corpus.librsf_input, inp)
    shutil.copy(corpus.librsf_truth, truth)
    out = folder / 'out_bag'
    protect, stale, extra, expect, allowed = [inp, truth], [], [], (4,), []
    out_named = None
    if kind == 'out_existing_folder':
        out.mkdir()
        (out / 'keep.txt').write_text('keep\n')
        protect.append(out / 'keep.txt')
    elif kind == 'out_existing_file':
        out.write_text('keep\n')
        protect.append(out)
    elif kind == 'out_unwritable':
        out = unwritable_folder(folder) / 'out_bag'
    elif kind == 'out_through_file':
        blocker = folder / 'a_file'
        blocker.write_text('keep\n')
        protect.append(blocker)
        out = blocker / 'out_bag'
    elif kind == 'json_existing':
        js = folder / 'summary.json'
        js.write_text('{"keep": true}\n')
        protect.append(js)
        extra = ['--json', str(js)]
        out_named = js
    else:                                   # a killed earlier run left its partial bag
        for n in range(int(rng.integers(1, 4))):
            p = folder / f'.out_bag.partial-{rng.integers(1 << 30):x}'
            p.mkdir()
            (p / 'junk.mcap').write_bytes(rng.bytes(4096))
            stale.append(p)
        expect, allowed = (0,), [out]
    return FileCase('convert', f'output_{kind}',
                    ['--input', str(inp), '--truth', str(truth), '--out', str(out), '--quiet',
                     *extra], expect,
                    names=named(out_named or out),
                    protect=protect, watch=[folder], allowed=allowed, stale=stale)
