"""Run every benchmark suite, or those named: `python -m bench [suite ...]`."""
import importlib
import sys

SUITES = []


def main(argv: list[str]) -> None:
    for name in argv or SUITES:
        print(f'== {name}', flush=True)
        importlib.import_module(f'bench.{name}').main()


if __name__ == '__main__':
    main(sys.argv[1:])
