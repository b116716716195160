"""The documentation stays usable: README.md short, every relative link (and its #anchor) in
README.md, BENCHMARKS.md and docs/*.md resolves inside the repository, the two commands stay on
top of the README and in CI, and every verb and --flag in the CLI tables of README.md and
docs/cli.md is real (read from the argparse parser of nrsfm_ros.cli; no ROS needed)."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from nrsfm_ros.cli import _parser

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / 'README.md'
DOCS = sorted([README, ROOT / 'BENCHMARKS.md', *(ROOT / 'docs').glob('*.md')])
MAX_README_LINES = 200
TWO_COMMANDS = ('./launch_scripts/demo.sh', './launch_scripts/test.sh')

LINK = re.compile(r'!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+"[^"]*")?\s*\)')
FENCE = re.compile(r'^(```|~~~).*?^\1[^\n]*$', re.S | re.M)
CODE_SPAN = re.compile(r'(`+)(?:(?!\1).)+?\1', re.S)
HEADING = re.compile(r'^#{1,6}\s+(.+?)\s*#*\s*$', re.M)
FLAG = re.compile(r'(?<![\w-])--[a-z][a-z0-9-]*')


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code spans (links there are not links)."""
    return CODE_SPAN.sub('', FENCE.sub('', text))


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to '-', '-N' repeats."""
    seen: dict[str, int] = {}
    out = set()
    for title in HEADING.findall(FENCE.sub('', path.read_text(encoding='utf-8'))):
        slug = re.sub(r'[^\w\- ]', '', title.strip().lower()).replace(' ', '-')
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f'{slug}-{n}')
    return out


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    # argparse has no public accessor for its sub-commands
    actions = [a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction)]
    assert len(actions) == 1
    return dict(actions[0].choices)


def _verb_rows(path: Path) -> list[tuple[str, str]]:
    """(verb, whole row) for every row of the tables whose header starts with '| verb |'."""
    rows, in_table = [], False
    for line in path.read_text(encoding='utf-8').splitlines():
        if line.startswith('| verb |'):
            in_table = True
            continue
        if not line.startswith('|'):
            in_table = False
            continue
        if in_table and not set(line) <= set('|-: '):
            m = re.match(r'\|\s*`([^`]+)`\s*\|', line)
            assert m, f'{path.name}: verb table row without a `verb` first cell: {line}'
            rows.append((m.group(1), line))
    return rows


def test_readme_is_short():
    n = len(README.read_text(encoding='utf-8').splitlines())
    assert n <= MAX_README_LINES, f'README.md has {n} lines (at most {MAX_README_LINES}): ' \
        'move detail to BENCHMARKS.md or docs/'


def test_two_commands_on_top_and_in_ci():
    head = README.read_text(encoding='utf-8').splitlines()[:20]
    for cmd in TWO_COMMANDS:
        assert any(line.startswith(cmd + ' ') for line in head), f'{cmd} not on top of README'
    ci = (ROOT / '.ci' / 'run').read_text(encoding='utf-8')
    assert re.search(r'^bash launch_scripts/test\.sh\s*$', ci, re.M), '.ci/run: test command'


@pytest.mark.parametrize('doc', DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc):
    bad = []
    for target in LINK.findall(_prose(doc.read_text(encoding='utf-8'))):
        if re.match(r'^[a-z][a-z0-9+.-]*:', target):      # http:, https:, mailto: ...
            continue
        path_part, _, anchor = target.partition('#')
        dest = (doc.parent / path_part).resolve() if path_part else doc
        if not dest.is_relative_to(ROOT) or not dest.exists():
            bad.append(f'{target} (no such file in the repository)')
        elif anchor and dest.suffix == '.md' and anchor not in _anchors(dest):
            bad.append(f'{target} (no heading #{anchor} in {dest.name})')
    assert not bad, f'{doc.name}: broken links: {bad}'


@pytest.mark.parametrize('doc', [README, ROOT / 'docs' / 'cli.md'], ids=lambda p: p.name)
def test_cli_tables_name_real_verbs_and_flags(doc):
    verbs = _subparsers()
    rows = _verb_rows(doc)
    assert rows, f'{doc.name}: no verb table'
    for verb, row in rows:
        assert verb in verbs, f'{doc.name}: `{verb}` is not a nrsfm-ros verb ({sorted(verbs)})'
        options = verbs[verb]._option_string_actions
        unknown = [f for f in FLAG.findall(row) if f not in options]
        assert not unknown, f'{doc.name}: nrsfm-ros {verb} has no {unknown}'
    missing = sorted(set(verbs) - {v for v, _ in rows})
    assert not missing, f'{doc.name}: verbs missing from the table: {missing}'
