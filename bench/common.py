"""Timing and reporting shared by every benchmark suite.

Each case prints one line (median, p95, sustained rate, the reference next to it)
and appends one JSON object to bench-results.jsonl so runs can be compared.
"""
import json
import platform
import time
from pathlib import Path
from typing import Callable

import numpy as np

RESULTS = Path('bench-results.jsonl')


def timeit(fn: Callable[[], object], repeat: int = 200, warmup: int = 5) -> np.ndarray:
    """Call fn warmup + repeat times; return the repeat durations in milliseconds."""
    for _ in range(warmup):
        fn()
    out = np.empty(repeat)
    for k in range(repeat):
        t0 = time.perf_counter()
        fn()
        out[k] = (time.perf_counter() - t0) * 1e3
    return out


def summary(ms: np.ndarray) -> tuple[float, float]:
    """Median and 95th percentile of durations in ms."""
    return float(np.median(ms)), float(np.percentile(ms, 95))


def report(suite: str, case: str, ms: np.ndarray, reference: str | None = None,
           ref_ms: np.ndarray | None = None, **extra: object) -> dict:
    """Print one case and append it to bench-results.jsonl.

    `ms` are per-operation times; the sustained rate is 1000 / median. `extra`
    carries accuracy figures or anything else the case measures.
    """
    med, p95 = summary(ms)
    row: dict = {'suite': suite, 'case': case, 'median_ms': round(med, 6),
                 'p95_ms': round(p95, 6), 'rate_hz': round(1e3 / med, 1) if med > 0 else None,
                 'reference': reference, 'ref_median_ms': None,
                 'machine': f'{platform.machine()} {platform.processor() or ""}'.strip()}
    line = f'{case:<34} median {med:9.3f} ms  p95 {p95:9.3f} ms  {row["rate_hz"]:>9} Hz'
    if ref_ms is not None:
        rmed, rp95 = summary(ref_ms)
        row['ref_median_ms'] = round(rmed, 6)
        row['ref_p95_ms'] = round(rp95, 6)
        line += f'   | {reference}: median {rmed:.3f} ms  p95 {rp95:.3f} ms'
    row.update(extra)
    if extra:
        line += '   ' + ' '.join(f'{k}={v}' for k, v in extra.items())
    print(line, flush=True)
    with RESULTS.open('a') as f:
        f.write(json.dumps(row) + '\n')
    return row
