"""README.md and docs/*.md: every relative link and #anchor resolves, and every ```python
block runs as written (each on its own, from the checkout, writing nothing into it).

Truth for the anchors: GitHub's heading slugs (lower case, punctuation dropped, spaces to
hyphens, -1, -2 ... for repeats), checked on anchors GitHub generates for these headings.
A block fenced as ```python no-run is shown, not run.
"""
import os
import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]
BLOCK = re.compile(r'^```python[ \t]*(?P<tag>[^\n]*)\n(?P<code>.*?)^```', re.M | re.S)
CODE_SPAN = re.compile(r'(`+)(.+?)\1')
LINK = re.compile(r'\[(?:[^\[\]]|\[[^\]]*\])*\]\((?P<target>[^)\s]+)(?:\s+"[^"]*")?\)')
HEADING = re.compile(r'^#{1,6}[ \t]+(?P<text>.+?)[ \t]*#*[ \t]*$')
# What an example may leave behind in the checkout: caches and the installs.
UNTRACKED = ('.git', '.venv', 'build', '__pycache__', '.pytest_cache', '.hypothesis')


def prose(text: str) -> list[tuple[int, str]]:
    """(line number, line) of the lines outside fenced code blocks."""
    out, fence = [], None
    for n, line in enumerate(text.split('\n'), 1):
        marker = re.match(r'^[ \t]*(`{3,}|~{3,})', line)
        if marker and (fence is None or marker[1].startswith(fence)):
            fence = marker[1] if fence is None else None
        elif fence is None:
            out.append((n, line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text (before the -N of repeats)."""
    text = CODE_SPAN.sub(lambda m: m[2], heading)
    text = re.sub(r'!?\[([^\]]*)\]\([^)]*\)', r'\1', text).strip().lower()
    kept = (c for c in text
            if c in ' -' or unicodedata.category(c)[0] in 'LMN' or unicodedata.category(c) == 'Pc')
    return ''.join(kept).replace(' ', '-')


def anchors(text: str) -> set[str]:
    """Every anchor GitHub makes for the page's headings."""
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose(text):
        m = HEADING.match(line)
        if not m:
            continue
        base = slug(m['text'])
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f'{base}-{n}')
    return out


def links(text: str) -> list[tuple[int, str]]:
    """(line number, target) of every link and image outside code."""
    return [(n, m['target']) for n, line in prose(text)
            for m in LINK.finditer(CODE_SPAN.sub('', line))]


def broken_links(page: Path) -> list[str]:
    """The page's relative links whose file or #anchor does not exist."""
    bad = []
    for n, target in links(page.read_text()):
        if re.match(r'^[a-z][a-z0-9+.-]*:', target):     # https:, mailto: ...
            continue
        path, _, anchor = target.partition('#')
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(f'{page.name}:{n}: {target}: no such file')
        elif anchor and dest.suffix == '.md' and anchor not in anchors(dest.read_text()):
            bad.append(f'{page.name}:{n}: {target}: no heading #{anchor} in {dest.name}')
    return bad


def blocks(page: Path) -> list[tuple[int, str]]:
    """(line number, code) of every python block not fenced as `python no-run`."""
    text = page.read_text()
    return [(text[:m.start()].count('\n') + 1, m['code']) for m in BLOCK.finditer(text)
            if 'no-run' not in m['tag']]


def checkout_files() -> dict[str, tuple[int, int]]:
    """Size and modification time of every file in the checkout but caches and installs."""
    out = {}
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if not d.startswith(UNTRACKED)]
        for f in files:
            st = os.stat(os.path.join(folder, f))
            out[os.path.relpath(os.path.join(folder, f), ROOT)] = (st.st_size, st.st_mtime_ns)
    return out


def test_slugs_are_githubs():
    assert slug('TF frames (`frames_node`)') == 'tf-frames-frames_node'
    assert slug('MAVLink relay: velocity commands to ArduPilot / PX4') == \
        'mavlink-relay-velocity-commands-to-ardupilot--px4'
    assert slug('Ubuntu 24.04 and rosdep') == 'ubuntu-2404-and-rosdep'
    assert slug('Bags: `bag_play` and `bag_record`') == 'bags-bag_play-and-bag_record'
    assert slug('Parameters of `config/onboard.yaml`') == 'parameters-of-configonboardyaml'
    assert slug('Visión a bordo') == 'visión-a-bordo'
    assert anchors('# A\n## Frames\n```sh\n# Frames\n```\n### Frames\n') == {'a', 'frames', 'frames-1'}


def test_the_check_finds_what_is_broken(tmp_path):
    (tmp_path / 'other.md').write_text('# Other page\n\n## Its part\n')
    (tmp_path / 'page.md').write_text(
        '# Page\n\n[ok](other.md) [ok](other.md#its-part) [ok](#page) [web](https://example.org/x)\n'
        '![missing](nope.png) [no file](gone.md) [no anchor](other.md#nothing) [here](#nowhere)\n'
        '`[in code](gone.md)`\n```\n[in a block](gone.md)\n```\n')
    assert broken_links(tmp_path / 'page.md') == [
        'page.md:4: nope.png: no such file', 'page.md:4: gone.md: no such file',
        'page.md:4: other.md#nothing: no heading #nothing in other.md',
        'page.md:4: #nowhere: no heading #nowhere in page.md']


@pytest.mark.parametrize('page', PAGES, ids=lambda p: p.name)
def test_links_resolve(page):
    assert broken_links(page) == []


def test_the_readme_links_every_page():
    linked = {(ROOT / target.partition('#')[0]).resolve()
              for _, target in links((ROOT / 'README.md').read_text())}
    assert set(PAGES[1:]) <= linked


def test_the_pages_have_their_examples():
    assert len(blocks(ROOT / 'docs' / 'library.md')) >= 5
    assert len(blocks(ROOT / 'docs' / 'onboard.md')) >= 1


@pytest.mark.parametrize('page, line, code', [(p, n, c) for p in PAGES for n, c in blocks(p)],
                         ids=lambda v: v.name if isinstance(v, Path) else
                         f'line{v}' if isinstance(v, int) else '')
def test_example_runs(page, line, code, monkeypatch):
    monkeypatch.chdir(ROOT)
    before = checkout_files()
    exec(compile(code, f'{page.relative_to(ROOT)}:{line}', 'exec'), {'__name__': '__docs__'})
    assert checkout_files() == before, 'the example wrote into the checkout'
