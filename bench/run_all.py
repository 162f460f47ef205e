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
# Runs of a benchmark beside its default one, each with a name for its report: the family
# bench's acceptance table (issue 47: both declared sets, both rates, against the switch;
# docs/model.md §3.1), which fails `make bench` when a set misses its targets.
EXTRA_RUNS = {
    'bench_memory_families': [
        ('bench_memory_families_acceptance',
         ['--against-switch', '--forms', 'sigmoid', '--set', 'both', '--rate-hz', '20', '50']),
    ],
}


def main(argv: list[str]) -> int:
    selected = set(argv)
    scripts = sorted(p for p in HERE.glob('bench_*.py') if not selected or p.stem in selected)
    if not scripts:
        print(f'no benchmark matches {sorted(selected)}', file=sys.stderr)
        return 2
    results = HERE / 'results'
    results.mkdir(exist_ok=True)
    runs = [(script.stem, script, []) for script in scripts]
    runs += [(name, script, args) for script in scripts
             for name, args in EXTRA_RUNS.get(script.stem, [])]
    failed = []
    for name, script, args in runs:
        print(f'\n=== {" ".join([name, *args])} ===', flush=True)
        start = time.monotonic()
        proc = subprocess.run([sys.executable, str(script), *args], capture_output=True,
                              text=True, check=False)
        elapsed = time.monotonic() - start
        report = proc.stdout + (f'\n[stderr]\n{proc.stderr}' if proc.returncode else '')
        print(report, end='')
        (results / f'{name}.txt').write_text(report)
        print(f'--- {name}: exit {proc.returncode} in {elapsed:.1f} s', flush=True)
        if proc.returncode:
            failed.append(name)
    if failed:
        print(f'\nfailed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
