"""``terrain-bench SUITE [--quick] [--json PATH]``: run one benchmark suite.

A suite is a module ``terrain_perception.bench.<suite>`` (dashes become underscores) with
``run(args) -> dict`` (prints its own table, returns JSON-able figures) and optionally
``add_arguments(parser)`` for suite-specific options.
"""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys
import time
from pathlib import Path

import terrain_perception.bench as bench_pkg

_NOT_SUITES = {'runner', 'common'}


def available_suites() -> list[str]:
    return sorted(m.name.replace('_', '-') for m in pkgutil.iter_modules(bench_pkg.__path__)
                  if not m.name.startswith('_') and m.name not in _NOT_SUITES)


def main(argv=None) -> int:
    suites = available_suites()
    first = argparse.ArgumentParser(prog='terrain-bench', add_help=False)
    first.add_argument('suite', nargs='?')
    known, _ = first.parse_known_args(argv)
    if known.suite is None or known.suite not in suites:
        msg = f'available suites: {", ".join(suites) or "(none)"}'
        if known.suite not in (None, '-h', '--help'):
            print(f'terrain-bench: unknown suite {known.suite!r}; {msg}', file=sys.stderr)
            return 2
        print(f'usage: terrain-bench SUITE [--quick] [--json PATH] [suite options]\n{msg}')
        return 0 if known.suite else 2
    module = importlib.import_module(f'terrain_perception.bench.{known.suite.replace("-", "_")}')
    parser = argparse.ArgumentParser(prog=f'terrain-bench {known.suite}',
                                     description=(module.__doc__ or '').strip().splitlines()[0]
                                     if module.__doc__ else None)
    parser.add_argument('suite')
    parser.add_argument('--quick', action='store_true',
                        help='smaller problem sizes (CI / smoke run, under 2 minutes)')
    parser.add_argument('--json', type=Path, default=None, help='write the figures as JSON here')
    if hasattr(module, 'add_arguments'):
        module.add_arguments(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    try:
        figures = module.run(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f'terrain-bench {known.suite}: {exc}', file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - t0
    print(f'\n[{known.suite}] finished in {elapsed:.1f} s')
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = dict(figures)
        payload.setdefault('_meta', {'suite': known.suite, 'quick': bool(args.quick),
                                     'elapsed_s': round(elapsed, 2)})
        args.json.write_text(json.dumps(payload, indent=2, sort_keys=True, default=float))
        print(f'[{known.suite}] figures written to {args.json}')
    # A suite stopped by Ctrl-C / SIGTERM returns the figures of what it finished, marked
    # 'stopped'; the exit code still says it did not run to its end.
    return 130 if figures.get('stopped') else 0


if __name__ == '__main__':
    sys.exit(main())
