"""docs/rinex.md shows the figures of docs/results/rinex.json (written by
``python -m gnsscam_ros.evaluation.rinex_report``), never typed ones."""
import json
from pathlib import Path

from gnsscam_ros.evaluation.rinex_report import render_tables

ROOT = Path(__file__).resolve().parents[1]


def test_docs_tables_are_the_result_file():
    result = json.loads((ROOT / 'docs' / 'results' / 'rinex.json').read_text())
    assert result['orbits'] and result['stations'] and result['command']
    assert render_tables(result) in (ROOT / 'docs' / 'rinex.md').read_text()
