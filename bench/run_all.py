"""`make bench`: run every bench/bench_*.py in turn and keep their reports.

Each benchmark prints its own table, with figures as ratios against a baseline it
measures in the same run (machines here are noisy, absolute numbers are not
comparable between runs). Reports are also written to bench/results/<name>.txt.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    selected = set(argv)
    scripts = sorted(p for p in HERE.glob('bench_*.py') if not selected or p.stem in selected)
    if not scripts:
        print(f'no benchmark matches {sorted(selected)}', file=sys.stderr)
        return 2
    results = HERE / 'results'
    results.mkdir(exist_ok=True)
    failed = []
    for script in scripts:
        print(f'\n=== {script.stem} ===', flush=True)
        start = time.monotonic()
        proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                              check=False)
        elapsed = time.monotonic() - start
        report = proc.stdout + (f'\n[stderr]\n{proc.stderr}' if proc.returncode else '')
        print(report, end='')
        (results / f'{script.stem}.txt').write_text(report)
        print(f'--- {script.stem}: exit {proc.returncode} in {elapsed:.1f} s', flush=True)
        if proc.returncode:
            failed.append(script.stem)
    if failed:
        print(f'\nfailed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
