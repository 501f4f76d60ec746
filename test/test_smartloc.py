"""smartLoc (libRSF text) loader: the committed excerpt and malformed input."""
import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT

from gnsscam_ros.datasets.errors import DatasetError
from gnsscam_ros.datasets.smartloc import discover_files, load_smartloc
from oracles import integrate_odometry

GOOD_PR = ('pseudorange3 0 19949087.65 25 14567933.92 2809850.97 21875628.07 12 1 85.1 49\n')
GOOD_ODOM = 'odom3 0 5.85 0 0 0 0 -0.0059 0.0025 0.0009 0.0009 4e-06 4e-06 4e-06\n'


def test_excerpt_loads(smartloc_excerpt):
    drive = smartloc_excerpt
    assert len(drive.gnss) == 284 and len(drive.odometry) == 284 and len(drive.truth) == 284
    assert drive.origin_llh is None
    counts = [e.n_sv for e in drive.gnss]
    assert min(counts) >= 7 and max(counts) <= 17
    assert set(np.unique(np.concatenate([e.system for e in drive.gnss]))) == {1, 4}
    stamps = np.array([e.stamp_ns for e in drive.gnss])
    assert np.all(np.diff(stamps) > 0)


def test_odometry_integrates_to_the_truth_path_length(smartloc_excerpt):
    drive = smartloc_excerpt
    motion = integrate_odometry(drive.odometry, drive.truth.stamp_ns[0],
                                drive.truth.stamp_ns[-1])
    path = np.sum(np.linalg.norm(np.diff(drive.truth.ecef_m, axis=0), axis=1))
    assert abs(motion.distance_m - path) < 0.02 * path


def test_discover_files_finds_input_and_truth():
    found_input, found_truth = discover_files(SMARTLOC_EXCERPT)
    assert found_input.name.endswith('_Input.txt') and found_truth.name.endswith('_GT.txt')


@pytest.mark.parametrize('bad_line,message', [
    ('pseudorange3 0 1 2 3\n', 'needs 11 fields, got 5'),
    ('pseudorange3 0 x 25 1 2 3 12 1 85 49\n', "pseudorange .* 'x' is not a number"),
    ('gyro3 0 1 2 3\n', "unknown record type 'gyro3'"),
    ('odom3 nan 1 0 0 0 0 0 0 0 0 0 0 0\n', r'time \[s\] is nan, not finite'),
])
def test_malformed_line_names_file_and_line(tmp_path, bad_line, message):
    path = tmp_path / 'run_Input.txt'
    path.write_text(GOOD_ODOM + GOOD_PR + bad_line)
    with pytest.raises(DatasetError, match=message) as info:
        load_smartloc(path)
    assert f'{path}:3:' in str(info.value)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(DatasetError, match='cannot open'):
        load_smartloc(tmp_path / 'absent_Input.txt')
    binary = tmp_path / 'bin_Input.txt'
    binary.write_bytes(b'\xff\xfe\x00garbage')
    with pytest.raises(DatasetError, match='not a text file'):
        load_smartloc(binary)


def test_epochs_out_of_order(tmp_path):
    later = GOOD_PR.replace('pseudorange3 0 ', 'pseudorange3 1 ')
    path = tmp_path / 'x_Input.txt'
    path.write_text(later + GOOD_PR)
    with pytest.raises(DatasetError, match='not in time order'):
        load_smartloc(path)


def test_nan_pseudorange_is_refused_at_load(tmp_path):
    # Refused where it is read (file and line), not left to the filter: a NaN that gets
    # through fails late, in the JSON writer, without saying where it came from.
    path = tmp_path / 'x_Input.txt'
    path.write_text(GOOD_PR.replace('19949087.65', 'nan'))
    with pytest.raises(DatasetError, match=r'x_Input.txt:1: pseudorange3: pseudorange .* '
                       'not finite'):
        load_smartloc(path)


def test_folder_without_input_file(tmp_path):
    with pytest.raises(DatasetError, match='expected exactly one'):
        discover_files(tmp_path)
