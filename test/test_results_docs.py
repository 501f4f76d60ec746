"""Every measured figure of docs/ and the README is the one its result file holds.

``docs/results.md`` and the README's results block are rendered by
``python -m gnsscam_ros.evaluation.docs`` from ``docs/results/*.json`` (each the ``--json``
of a command, with its date, machine and command line); these tests fail when a page
differs from what its files give, when a result file lacks its provenance, or when a figure
(an image) of the documentation is missing or is not one a result file names.
"""
import copy
import json
import re
import shutil
from pathlib import Path

import pytest

from gnsscam_ros.evaluation import docs

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'docs' / 'results'
IMAGE = re.compile(r'!\[[^\]]*\]\(([^)\s]+)\)')


def pages() -> list[Path]:
    return [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]


def test_every_result_file_says_when_where_and_how_it_was_made():
    results = docs.load_results(RESULTS)
    assert {'smartloc', 'robustness', 'rinex'} <= set(results), sorted(results)
    for name, result in results.items():
        assert re.match(r'\d{4}-\d\d-\d\dT', result['date']), name
        assert docs.command_of(result), name
        assert result.get('machine'), name


def test_generated_pages_are_their_result_files():
    rendered = docs.rendered_pages(ROOT, docs.load_results(RESULTS))
    stale = [str(p.relative_to(ROOT)) for p, text in rendered.items()
             if p.read_text(encoding='utf-8') != text]
    assert not stale, (f'{stale} differ from docs/results/*.json: run '
                       'python -m gnsscam_ros.evaluation.docs')


def test_a_changed_result_changes_the_page():
    """The comparison above bites: one figure moved in a result file moves the page."""
    results = docs.load_results(RESULTS)
    text = docs.render_results(results)
    moved = copy.deepcopy(results)
    moved['smartloc']['rmse_2d_m'] += 1.234
    changed = docs.render_results(moved)
    assert changed != text
    assert f"{moved['smartloc']['rmse_2d_m']:.2f}" in changed


def test_every_image_exists_and_every_figure_comes_from_a_result_file():
    results = docs.load_results(RESULTS)
    for page in pages():
        for target in IMAGE.findall(page.read_text(encoding='utf-8')):
            assert (page.parent / target).is_file(), f'{page.name}: {target} is missing'
    sources = docs.figure_sources(results)
    figures = sorted(str(p.relative_to(ROOT / 'docs')) for p in (ROOT / 'docs').rglob('*.png'))
    orphans = [f for f in figures if f not in sources]
    assert not orphans, f'figures no result file names (not generated?): {orphans}'


def test_check_mode_reports_a_stale_page_and_a_file_without_provenance(tmp_path, capsys):
    shutil.copy(ROOT / 'README.md', tmp_path / 'README.md')
    shutil.copytree(RESULTS, tmp_path / 'docs' / 'results')
    assert docs.main(['--root', str(tmp_path)]) == docs.EXIT_OK
    assert docs.main(['--root', str(tmp_path), '--check']) == docs.EXIT_OK
    page = tmp_path / 'docs' / 'results.md'
    page.write_text(page.read_text().replace('|', '/', 3))
    assert docs.main(['--root', str(tmp_path), '--check']) == docs.EXIT_STALE
    assert 'results.md differs' in capsys.readouterr().err
    bare = json.loads((RESULTS / 'smartloc.json').read_text())
    for key in ('date', 'command_line', 'command'):
        bare.pop(key, None)
    (tmp_path / 'docs' / 'results' / 'smartloc.json').write_text(json.dumps(bare))
    assert docs.main(['--root', str(tmp_path), '--check']) == docs.EXIT_INPUT
    assert 'smartloc.json: no date or command line' in capsys.readouterr().err


@pytest.mark.parametrize('block', ['results'])
def test_readme_block_markers_are_there_once(block):
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    assert text.count(docs.BEGIN.format(block)) == 1
    assert text.count(docs.END.format(block)) == 1
