"""Android GnssLogger raw rows -> pseudoranges (datasets.android), against the GSDC's own
values, and the android command's refusals."""
import csv
from pathlib import Path

import numpy as np
import pytest

from gnsscam_ros.bags import convert_cli
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.snapshot import solve_snapshot
from gnsscam_ros.core.types import GPS, GnssEpoch
from gnsscam_ros.datasets.android import (SYSTEM_OF_CONSTELLATION, read_android_log,
                                          read_ground_truth)
from gnsscam_ros.datasets.errors import DatasetError

DATA = Path(__file__).resolve().parent / 'data' / 'android'
GSDC_2022 = DATA / 'google_decimeter_2022_device_gnss.csv'
PIXEL_2023 = DATA / 'google_decimeter_2023_2023-09-07-18-59-us-ca_pixel7pro_gnss_log.txt'
NAV_OTHER_DAY = Path(__file__).resolve().parent / 'data' / 'rinex' / 'brdc1180.21n'
L1_SIGNALS = ('GPS_L1', 'GAL_E1', 'BDS_B1I', 'GLO_G1')


def gsdc_rows():
    with GSDC_2022.open(newline='') as handle:
        return [r for r in csv.DictReader(handle)
                if r['RawPseudorangeMeters'] and r['SignalType'] in L1_SIGNALS]


def test_raw_pseudoranges_equal_gsdc_up_to_the_full_bias_change():
    log = read_android_log(GSDC_2022)
    rows = gsdc_rows()
    full_bias_0 = int(rows[0]['FullBiasNanos'])
    mine = {}
    for epoch in log.epochs:
        for system, prn, pr in zip(epoch.system, epoch.prn, epoch.pr_m):
            mine[(round(epoch.gps_s), int(system), int(prn))] = pr
    compared = 0
    for r in rows:
        key = (round(float(r['ArrivalTimeNanosSinceGpsEpoch']) / 1e9),
               SYSTEM_OF_CONSTELLATION[int(r['ConstellationType'])], int(r['Svid']))
        # GSDC keeps the first FullBiasNanos for the whole log; this reader each row's.
        shift_m = (int(r['FullBiasNanos']) - full_bias_0) * 1e-9 * 299792458.0
        assert mine[key] == pytest.approx(float(r['RawPseudorangeMeters']) - shift_m, abs=1e-3)
        compared += 1
    assert compared >= 100


def test_gsdc_corrections_on_these_pseudoranges_fix_the_phone():
    """GSDC's satellite positions and corrections applied to the pseudoranges read here
    give a fix within metres of the ground truth (a phone under open sky)."""
    log = read_android_log(GSDC_2022)
    truth = read_ground_truth(DATA / 'google_decimeter_2022_ground_truth.csv')
    rows = [r for r in gsdc_rows() if r['SignalType'] == 'GPS_L1']
    errors = []
    for epoch in log.epochs:
        t = round(epoch.gps_s)
        mine = {int(p): pr for s, p, pr in zip(epoch.system, epoch.prn, epoch.pr_m) if s == GPS}
        here = [r for r in rows if round(float(r['ArrivalTimeNanosSinceGpsEpoch']) / 1e9) == t]
        if len(here) < 5:
            continue
        pr = np.array([mine[int(r['Svid'])] + float(r['SvClockBiasMeters'])
                       - float(r['IonosphericDelayMeters']) - float(r['TroposphericDelayMeters'])
                       for r in here])
        sv = np.array([[float(r[f'SvPosition{a}EcefMeters']) for a in 'XYZ'] for r in here])
        k = len(here)
        fix = solve_snapshot(GnssEpoch(epoch.stamp_ns, sv, pr, np.full(k, 10.0),
                                       np.array([int(r['Svid']) for r in here]),
                                       np.full(k, GPS), np.full(k, np.nan), np.full(k, np.nan)))
        i = int(np.argmin(np.abs(truth.stamp_ns - epoch.stamp_ns)))
        assert abs(truth.stamp_ns[i] - epoch.stamp_ns) < 1e9       # UTC stamps agree
        enu = LocalFrame.from_ecef(truth.ecef_m[i]).ecef_to_enu(fix.ecef_m)
        errors.append(np.hypot(enu[0], enu[1]))
    assert len(errors) >= 4
    assert np.sqrt(np.mean(np.square(errors))) < 10.0


def test_pixel_log_reads_l1_epochs_and_counts_the_rest():
    log = read_android_log(PIXEL_2023)
    assert len(log.epochs) == 5 and log.rows == 180
    assert log.rows_not_used.get('other_signal', 0) > 0       # L5 / E5a rows
    for epoch in log.epochs:
        gps = epoch.pr_m[epoch.system == GPS]
        assert gps.size >= 8 and np.all((gps > 1.9e7) & (gps < 2.7e7))


def test_android_command_refuses_navigation_of_another_day(tmp_path, capsys):
    bag = tmp_path / 'bag'
    code = convert_cli.main(['android', '--log', str(PIXEL_2023), '--nav', str(NAV_OTHER_DAY),
                             '--out', str(bag), '--quiet'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == convert_cli.EXIT_INPUT
    assert len(err) == 1 and 'another day' in err[0]
    assert not bag.exists()


def test_android_log_without_raw_header(tmp_path):
    bad = tmp_path / 'log.txt'
    bad.write_text('# Fix,Provider\nFix,gps\n')
    with pytest.raises(DatasetError, match='log.txt: no "# Raw," header'):
        read_android_log(bad)
