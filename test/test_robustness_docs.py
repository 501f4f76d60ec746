"""docs/robustness.md shows the figures of docs/results/robustness.json (written by
``gnsscam_eval robustness --json``), never typed ones."""
import json
from pathlib import Path

from gnsscam_ros.evaluation.robustness_cli import robustness_table

ROOT = Path(__file__).resolve().parents[1]


def test_docs_table_is_the_result_file():
    result = json.loads((ROOT / 'docs' / 'results' / 'robustness.json').read_text())
    assert result['command_line'].startswith('gnsscam_eval robustness') and result['date']
    text = (ROOT / 'docs' / 'robustness.md').read_text()
    assert robustness_table(result) in text
    assert result['command_line'] in text
