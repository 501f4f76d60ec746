"""docs/robustness.md shows the figures of docs/results/robustness.json (written by
``gnsscam_eval robustness --json``), never typed ones."""
import json
from pathlib import Path

from gnsscam_ros.evaluation.robustness_cli import robustness_table

ROOT = Path(__file__).resolve().parents[1]


def test_docs_tables_are_the_result_files():
    text = (ROOT / 'docs' / 'robustness.md').read_text()
    files = sorted((ROOT / 'docs' / 'results').glob('robustness*.json'))
    assert [p.name for p in files][:1] == ['robustness.json']
    for path in files:
        result = json.loads(path.read_text())
        assert result['command_line'].startswith('gnsscam_eval robustness') and result['date']
        assert robustness_table(result) in text, path.name
        assert result['command_line'] in text, path.name
