"""A campaign folder: every case streamed to disk as it finishes, resumed by the next run.

Layout of ``--out DIR``::

    DIR/cases/<tag>.npz     the case's per-epoch series (figures), written first
    DIR/cases/<tag>.json    its metrics and the campaign fingerprint, written last
    DIR/campaign.json       the summary of the whole grid (written at the end)
    DIR/runs.csv            one row per case: counts and RMSE
    DIR/intervals.csv       one row per (method, case, rate): counts and intervals

Every file is written atomically (``io.atomic``), so a case is finished exactly when its
JSON exists: a campaign killed at case 150 of 200 leaves 150 complete cases and no partial
file, and the same command run again computes only the other 50. The JSON carries the
fingerprint of the campaign's configuration (``campaign_grid.fingerprint``); a folder
holding cases of another configuration is refused, not mixed (``--restart`` empties it).
The store runs on the machine that runs the campaign command: workers never write here.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.atomic import write_json_atomic, write_npz_atomic
from .campaign_grid import CaseKey

#: Per-epoch arrays of a case kept for the figures.
SERIES_KEYS = ('t_s', 'estimate', 'truth', 'bound', 'reference', 'error_m',
               'protection_level_m', 'integrity')


def restore_infinities(value):
    """``value`` read back from JSON with the ``"inf"``/``"-inf"`` strings of
    :func:`~gnsscam_ros.io.atomic.write_json_atomic` as floats again."""
    if isinstance(value, dict):
        return {k: restore_infinities(v) for k, v in value.items()}
    if isinstance(value, list):
        return [restore_infinities(v) for v in value]
    if value in ('inf', '-inf'):
        return float(value)
    return value


class CampaignStoreError(Exception):
    """The campaign folder cannot be used (another configuration, unreadable files)."""


class CampaignStore:
    """The finished cases of one campaign configuration in a folder.

    Args:
        folder: The campaign folder (created).
        fingerprint: The campaign's fingerprint.
        restart: Remove the cases found there first (only the files this store writes).

    Raises:
        CampaignStoreError: The folder holds cases of another fingerprint (and not
            ``restart``), or cannot be created.
    """

    def __init__(self, folder: Path, fingerprint: str, restart: bool = False):
        self.folder = Path(folder)
        self.cases_dir = self.folder / 'cases'
        self.fingerprint = fingerprint
        try:
            self.cases_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise CampaignStoreError(f'cannot create {self.cases_dir}: '
                                     f'{err.strerror or err}') from err
        if restart:
            for path in self.cases_dir.iterdir():
                if path.suffix in ('.json', '.npz') and path.stem.startswith('s'):
                    path.unlink()

    def finished(self, keys: list[CaseKey]) -> dict[CaseKey, dict]:
        """Metrics of the cases of ``keys`` already in the folder (``{key: metrics}``).

        Raises:
            CampaignStoreError: A case file of another fingerprint, or an unreadable one.
        """
        done = {}
        for key in keys:
            path = self.cases_dir / f'{key.tag}.json'
            if not path.exists():
                continue
            try:
                data = json.loads(path.read_text(encoding='utf-8'))
                fingerprint, metrics = data['fingerprint'], data['metrics']
            except (OSError, ValueError, KeyError, TypeError) as err:
                raise CampaignStoreError(f'{path}: unreadable case file ({err}); remove it '
                                         'or pass --restart') from err
            if fingerprint != self.fingerprint:
                raise CampaignStoreError(
                    f'{self.folder} holds cases of another campaign configuration '
                    f'({path.name}: {fingerprint}, this one {self.fingerprint}); use another '
                    '--out or pass --restart to discard them')
            if not (self.cases_dir / f'{key.tag}.npz').exists():
                continue                   # figures lost: recompute the case
            done[key] = restore_infinities(metrics)
        return done

    def save(self, key: CaseKey, result: dict) -> None:
        """Write a finished case: its series, then its metrics (the JSON marks it done)."""
        series = result['series']
        write_npz_atomic(self.cases_dir / f'{key.tag}.npz',
                         **{k: np.asarray(series[k]) for k in SERIES_KEYS})
        write_json_atomic(self.cases_dir / f'{key.tag}.json',
                          {'fingerprint': self.fingerprint, 'case': key.as_dict(),
                           'metrics': result['metrics']}, force=True)

    def series(self, key: CaseKey) -> dict:
        """The per-epoch series of a finished case."""
        with np.load(self.cases_dir / f'{key.tag}.npz', allow_pickle=False) as data:
            return {k: data[k] for k in SERIES_KEYS}
