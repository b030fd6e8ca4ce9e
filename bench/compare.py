"""Before and after in one run: `python -m bench.compare [--rounds N] REV [suite ...]`.

Checks REV out into a temporary git worktree and runs the named suites (default:
convert fuzzy ground mavlink relay) against REV's package and against this checkout's, in
alternating rounds so that a change in the machine's load falls on both sides. Each
side runs its own benchmark code (a module REV lacks is taken from this checkout), in
a process whose PYTHONPATH puts that side's tree first, so its nodes too run that
side's code. Prints, per case, the median over the rounds of each side's median and
p95, and the change; appends one `compare` row per case to bench-results.jsonl.
"""
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.__main__ import SUITES
from bench.common import RESULTS

HERE = Path(__file__).resolve().parents[1]
DEFAULT_SUITES = ['convert', 'fuzzy', 'ground', 'mavlink', 'relay']
SIDE_TIMEOUT = 900.0     # s for one side's suites: a benchmark that hangs ends the side


def run_side(tree: Path, suites: list[str], out: Path) -> list[dict]:
    """`python -m bench SUITES` with `tree` first on the path, results in `out`; a run
    that fails or outlasts SIDE_TIMEOUT keeps the cases it finished."""
    out.mkdir(parents=True, exist_ok=True)
    results = out / RESULTS.name
    results.unlink(missing_ok=True)
    env = {**os.environ, 'PYTHONPATH': str(tree)}
    try:
        subprocess.run([sys.executable, '-m', 'bench', *suites], cwd=out, env=env, check=True,
                       stdout=subprocess.DEVNULL, timeout=SIDE_TIMEOUT)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as err:
        print(f'  {tree}: {err}; its finished cases are kept', flush=True)
    if not results.exists():
        return []
    return [json.loads(line) for line in results.read_text().splitlines()]


def worktree(rev: str, where: Path) -> Path:
    """REV checked out at `where`, with this checkout's suite list and the benchmark
    modules REV lacks."""
    subprocess.run(['git', '-C', str(HERE), 'worktree', 'add', '--detach', '--quiet', str(where),
                    rev], check=True)
    for module in (HERE / 'bench').glob('*.py'):
        if module.name == '__main__.py' or not (where / 'bench' / module.name).exists():
            shutil.copy(module, where / 'bench' / module.name)
    return where


def compare(rev: str, suites: list[str], rounds: int) -> None:
    with tempfile.TemporaryDirectory(prefix='uav_vs_compare_') as tmp:
        old = worktree(rev, Path(tmp) / 'tree')
        runs: dict[str, dict[str, list[dict]]] = {'before': {}, 'after': {}}
        try:
            for k in range(rounds):
                for side, tree in (('before', old), ('after', HERE)):
                    print(f'round {k + 1}/{rounds}: {side} ({rev if side == "before" else "HEAD"})',
                          flush=True)
                    for row in run_side(tree, suites, Path(tmp) / side):
                        runs[side].setdefault(row['case'], []).append(row)
        finally:
            subprocess.run(['git', '-C', str(HERE), 'worktree', 'remove', '--force', str(old)],
                           check=False)
    report(rev, runs)


def report(rev: str, runs: dict[str, dict[str, list[dict]]]) -> None:
    print(f'\n{"case":<36} {"before median / p95 ms":>24} {"after median / p95 ms":>24} '
          f'{"change":>8}')
    with RESULTS.open('a') as f:
        for case, after in runs['after'].items():
            before = runs['before'].get(case)
            a = [statistics.median(r[key] for r in after) for key in ('median_ms', 'p95_ms')]
            if not before:
                print(f'{case:<36} {"(not in " + rev + ")":>24} {a[0]:>12.4f} / {a[1]:<9.4f}')
                continue
            b = [statistics.median(r[key] for r in before) for key in ('median_ms', 'p95_ms')]
            change = (a[0] - b[0]) / b[0] * 100 if b[0] else float('nan')
            print(f'{case:<36} {b[0]:>12.4f} / {b[1]:<9.4f} {a[0]:>12.4f} / {a[1]:<9.4f} '
                  f'{change:>+7.1f}%')
            f.write(json.dumps({'suite': 'compare', 'case': case, 'before_rev': rev,
                                'before_median_ms': b[0], 'before_p95_ms': b[1],
                                'after_median_ms': a[0], 'after_p95_ms': a[1],
                                'change_pct': round(change, 2),
                                'rounds': len(after)}) + '\n')


def main(argv: list[str]) -> None:
    rounds = 3
    if argv[:1] == ['--rounds'] and len(argv) > 1:
        rounds, argv = int(argv[1]), argv[2:]
    if not argv:
        sys.exit('usage: python -m bench.compare [--rounds N] REV [suite ...]')
    suites = argv[1:] or DEFAULT_SUITES
    unknown = set(suites) - set(SUITES)
    if unknown:
        sys.exit(f'unknown suite(s) {sorted(unknown)}; known: {", ".join(SUITES)}')
    compare(argv[0], suites, rounds)


if __name__ == '__main__':
    main(sys.argv[1:])
