"""A campaign's cases as a grid: seeds (ranges and lists) x GNSS cases x methods.

``--seeds 1-200``, ``--seeds 1 2 3``, ``--seeds 1-10,20,30-35`` name seeds;
``--faults 0 2 4 6 9 --bias-m 100 200`` name the GNSS cases (0 faults is the NLOS-only
case, whatever the bias). A case is identified by :class:`CaseKey`; a campaign by the
fingerprint of what decides its results (:func:`fingerprint`), so that a campaign folder
is resumed only by the same campaign.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

#: Seeds accepted on the command line (drive seeds are non-negative).
MAX_SEED = 2 ** 31 - 1
#: A range wider than this is a typo, not a campaign.
MAX_SEEDS = 1_000_000
#: Version of the per-case files; a change makes older folders foreign.
CASE_FORMAT = 1


class GridError(ValueError):
    """A seed or case specification that cannot be parsed."""


def parse_seed_token(text: str) -> list[int]:
    """Seeds of one token: ``"7"``, ``"1-200"`` (inclusive) or comma lists of those.

    Raises:
        GridError: Not a seed, a reversed range, a negative or too large seed.
    """
    seeds: list[int] = []
    for part in text.split(','):
        part = part.strip()
        if not part:
            continue
        lo_text, sep, hi_text = part.partition('-')
        try:
            lo = int(lo_text)
            hi = int(hi_text) if sep else lo
        except ValueError:
            raise GridError(f'bad seed {part!r}: use N, A-B or lists such as 1-10,20')
        if not 0 <= lo <= hi <= MAX_SEED:
            raise GridError(f'bad seed range {part!r}: need 0 <= A <= B <= {MAX_SEED}')
        if hi - lo + 1 > MAX_SEEDS:
            raise GridError(f'seed range {part!r} has more than {MAX_SEEDS} seeds')
        seeds.extend(range(lo, hi + 1))
    if not seeds:
        raise GridError(f'no seed in {text!r}')
    return seeds


def parse_seeds(tokens) -> list[int]:
    """Seeds of several tokens, in order, each once."""
    return list(dict.fromkeys(s for token in tokens for s in parse_seed_token(str(token))))


def format_seeds(seeds) -> str:
    """Seeds as ranges: ``[1, 2, 3, 7]`` -> ``"1-3,7"``."""
    seeds = sorted(set(int(s) for s in seeds))
    parts, start = [], None
    for i, s in enumerate(seeds):
        if start is None:
            start = s
        if i + 1 == len(seeds) or seeds[i + 1] != s + 1:
            parts.append(f'{start}' if start == s else f'{start}-{s}')
            start = None
    return ','.join(parts)


def gnss_cases(faults, biases_m) -> list[tuple[int, float]]:
    """The GNSS cases of a grid: 0 faults once (NLOS only), then every bias x faults."""
    faults = list(dict.fromkeys(int(f) for f in faults))
    biases_m = list(dict.fromkeys(float(b) for b in biases_m))
    out = [(0, 0.0)] if 0 in faults else []
    out += [(f, b) for b in biases_m for f in faults if f != 0]
    if not out:
        raise GridError('no GNSS case: give --faults (and --bias-m for faults > 0)')
    return out


def case_tag(faults: int, bias_m: float) -> str:
    """Short file-name tag of a GNSS case."""
    return f'f{faults}_b{bias_m:g}' if faults else 'nlos'


@dataclass(frozen=True, order=True)
class CaseKey:
    """One run of a campaign: a drive seed, a GNSS case and a method."""

    seed: int
    faults: int
    bias_m: float
    method: str

    @property
    def tag(self) -> str:
        """File name stem: ``s<seed>_<case>_<method>``."""
        return f's{self.seed}_{case_tag(self.faults, self.bias_m)}_{self.method}'

    def as_dict(self) -> dict:
        return {'seed': self.seed, 'faults': self.faults, 'bias_m': self.bias_m,
                'method': self.method}


def case_grid(seeds, cases, methods) -> list[CaseKey]:
    """Every (seed, GNSS case, method), seed-major (a seed's cases share its camera)."""
    return [CaseKey(int(s), int(f), float(b), m) for s in seeds for f, b in cases
            for m in methods]


def fingerprint(config_flat: dict, duration_s: float | None) -> str:
    """Digest of what decides a case's results besides its key: the base configuration
    (every method's configuration derives from it), the drive length and the file format.
    """
    text = json.dumps({'config': config_flat, 'duration_s': duration_s,
                       'format': CASE_FORMAT}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
