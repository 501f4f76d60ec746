"""Broadcast orbits and clocks against precise products (SP3 orbits, RINEX CLK clocks).

Usage::

    python -m gnsscam_ros.evaluation.orbits --nav brdc1180.21n \\
        --sp3 COD0MGXFIN_20211180000_01D_05M_ORB.SP3 \\
        --clk COD0MGXFIN_20211180000_01D_30S_CLK.CLK [--json out.json]

Orbits: at every SP3 epoch, every satellite of a handled system with a usable broadcast
record: the 3D distance between ``core.ephemeris`` and the SP3 position [m] (the SP3
position is the centre of mass, the broadcast one the antenna phase centre: their
difference, up to ~1 m radially, is part of the figure). Clocks: the broadcast polynomial
(without group delay or relativistic term: the precise clocks refer, like it, to the
ionosphere-free P1/P2 combination and exclude the periodic relativistic term) against the
CLK file's ``AS`` records, after removing per epoch the mean over satellites (the precise
clocks' reference differs from GPS time by a common offset) [m].
"""
from __future__ import annotations

import argparse
import io
import sys
import warnings
from pathlib import Path

import numpy as np

from ..core.ephemeris import SPEED_OF_LIGHT_MPS, EphemerisSelector
from ..datasets.errors import DatasetError
from ..datasets.rinex import GPS_EPOCH, SYSTEM_OF_LETTER, gps_seconds, read_navigation
from ..datasets.rinex_check import open_text
from ..io.atomic import OutputExistsError, write_json_atomic


def read_sp3(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SP3 positions with georinex: (t,) GPS seconds, (s,) systems, (s,) PRNs,
    (t, s, 3) ECEF [m] (NaN where absent)."""
    import georinex
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            ds = georinex.load_sp3(io.StringIO(open_text(path)), None)
    except DatasetError:
        raise
    except Exception as err:
        raise DatasetError(f'{path}: not a readable SP3 file ({err})') from err
    names = np.asarray(ds.sv.values).astype(str)
    systems = np.array([SYSTEM_OF_LETTER.get(n[0], 0) for n in names])
    prns = np.array([int(n[1:]) for n in names])
    pos = np.asarray(ds['position'].values, dtype=float) * 1e3       # km -> m
    return gps_seconds(ds.time.values), systems, prns, pos


def read_clk(path: Path, letter: str = 'G') -> dict[float, dict[int, float]]:
    """Satellite clocks of a RINEX clock file: {GPS seconds: {prn: bias [s]}}."""
    out: dict[float, dict[int, float]] = {}
    in_body = False
    for i, line in enumerate(open_text(path).splitlines()):
        if not in_body:
            in_body = 'END OF HEADER' in line[60:]
            continue
        if not line.startswith(f'AS {letter}'):
            continue
        tokens = line.split()     # RINEX clock 3.04 widens the name field: by tokens
        try:
            prn = int(tokens[1][1:])
            y, mo, d, h, mi = (int(v) for v in tokens[2:7])
            sec = float(tokens[7])
            bias = float(tokens[9].replace('D', 'E'))
        except (ValueError, IndexError):
            raise DatasetError(f'{path}:{i + 1}: corrupt clock record') from None
        stamp = np.datetime64(f'{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}', 'ns')
        t = float((stamp - GPS_EPOCH).astype(np.int64) / 1e9) + sec
        out.setdefault(t, {})[prn] = bias
    return out


def compare(nav_paths: list[Path], sp3_path: Path, clk_path: Path | None,
            system: int = 1) -> dict:
    """The figures of the module docstring for one system (default GPS)."""
    nav = read_navigation(nav_paths)
    eph = nav.ephemerides.get(system)
    if eph is None:
        raise DatasetError(f"{', '.join(map(str, nav_paths))}: no records of system {system}")
    selector = EphemerisSelector(eph)
    times, systems, prns, pos = read_sp3(sp3_path)
    cols = np.flatnonzero(systems == system)
    errors = []
    for ti, t in enumerate(times):
        ok = cols[np.isfinite(pos[ti, cols, 0])]
        rows, codes = selector.select(prns[ok], t)
        use = codes == 0
        if not use.any():
            continue
        mine, _ = eph.position(rows[use], np.full(int(use.sum()), t))
        errors.append(np.linalg.norm(mine - pos[ti, ok[use]], axis=1))
    err = np.concatenate(errors) if errors else np.zeros(0)
    result = {'system': system, 'orbit_samples': int(err.size),
              'orbit_3d_rms_m': float(np.sqrt(np.mean(err ** 2))) if err.size else None,
              'orbit_3d_max_m': float(err.max()) if err.size else None}
    if clk_path is not None:
        letter = {v: k for k, v in SYSTEM_OF_LETTER.items()}[system]
        clocks = read_clk(clk_path, letter)
        residuals = []
        for t, by_prn in sorted(clocks.items()):
            prn = np.array(sorted(by_prn))
            rows, codes = selector.select(prn, t)
            use = codes == 0
            if use.sum() < 2:
                continue
            brdc = eph.clock_s(rows[use], np.full(int(use.sum()), t)) + eph.group_delay_s[
                rows[use]]
            diff = brdc - np.array([by_prn[p] for p in prn[use]])
            residuals.append((diff - diff.mean()) * SPEED_OF_LIGHT_MPS)
        res = np.concatenate(residuals) if residuals else np.zeros(0)
        result.update({'clock_samples': int(res.size),
                       'clock_rms_m': float(np.sqrt(np.mean(res ** 2))) if res.size else None,
                       'clock_rms_ns': (float(np.sqrt(np.mean(res ** 2)))
                                        / SPEED_OF_LIGHT_MPS * 1e9) if res.size else None})
    return result


def main(argv: list[str] | None = None) -> int:
    """Print (and with ``--json`` write) the comparison; exit 0, 3 bad input, 4 output."""
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.evaluation.orbits',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--nav', type=Path, action='append', required=True)
    parser.add_argument('--sp3', type=Path, required=True)
    parser.add_argument('--clk', type=Path)
    parser.add_argument('--json', type=Path)
    args = parser.parse_args(argv)
    try:
        result = compare(args.nav, args.sp3, args.clk)
    except DatasetError as err:
        print(f'orbits: {err}', file=sys.stderr)
        return 3
    print(' '.join(f'{k}={v:.3f}' if isinstance(v, float) else f'{k}={v}'
                   for k, v in result.items()))
    if args.json is not None:
        try:
            write_json_atomic(args.json, result)
        except (OSError, OutputExistsError, ValueError) as err:
            print(f'orbits: cannot write {args.json}: {err}', file=sys.stderr)
            return 4
    return 0


if __name__ == '__main__':
    sys.exit(main())
