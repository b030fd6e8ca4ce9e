"""Run every benchmark suite, or those named: `python -m bench [suite ...]`.

A suite is an area of the package; each of its modules times its own cases and
appends them to bench-results.jsonl.
"""
import importlib
import sys

SUITES = {
    'ground': ['ground', 'ground_detection', 'ground_latency'],
    'onboard': ['onboard_homography', 'onboard_pose', 'onboard_template', 'onboard_follow'],
    'fuzzy': ['fuzzy'],
    'mavlink': ['mavlink', 'mavlink_relay'],
    'relay': ['relay_command'],
    'bags': ['bags'],
    'convert': ['convert'],
    'graph': ['graph_latency', 'graph_scaling', 'live_view'],
    'sim': ['camera_effects'],
    'calibration': ['calibration'],
    'fusion': ['pose_filter'],
}


def main(argv: list[str]) -> None:
    unknown = set(argv) - set(SUITES)
    if unknown:
        sys.exit(f'unknown suite(s) {sorted(unknown)}; known: {", ".join(SUITES)}')
    for suite in argv or SUITES:
        print(f'== {suite}', flush=True)
        for module in SUITES[suite]:
            importlib.import_module(f'bench.{module}').main()


if __name__ == '__main__':
    main(sys.argv[1:])
