"""Point the ROS 2 wheels' exported CMake include paths at this venv.

The PyPI wheels were built under /opt/python/cp311-cp311/ and their CMake export
files still name that machine's Python include dir and numpy's include dir, so
`rosidl_generate_interfaces` fails at CMake's generate step. Rewrite both prefixes
once after install; running it again changes nothing.
"""

import pathlib
import re
import sys
import sysconfig

import numpy


def main(venv: str) -> int:
    py_include = sysconfig.get_paths()['include']
    np_include = numpy.get_include()
    pattern = re.compile(
        r'/opt/python/cp311-cp311/include/python3\.11|'
        r'/opt/python/cp311-cp311/lib/python3\.11/site-packages/numpy/_core/include')
    changed = 0
    for path in pathlib.Path(venv, 'share').glob('*/cmake/*.cmake'):
        text = path.read_text()
        fixed = pattern.sub(
            lambda m: np_include if 'numpy' in m.group(0) else py_include, text)
        if fixed != text:
            path.write_text(fixed)
            changed += 1
    leftover = [str(p) for p in pathlib.Path(venv, 'share').glob('*/cmake/*.cmake')
                if '/opt/python/cp311' in p.read_text()]
    print(f'fix_wheel_cmake: rewrote {changed} files')
    if leftover:
        print('fix_wheel_cmake: paths still pointing at the build machine in:', *leftover,
              sep='\n  ', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1]))
