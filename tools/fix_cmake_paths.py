"""Rewrite the build machine's include paths in the ROS wheels' CMake files.

The ROS 2 Jazzy wheels on PyPI export CMake targets whose include directories name the
machine that built them (/opt/python/cp3XX-cp3XX/include/python3.X and
.../site-packages/numpy/_core/include); CMake then refuses to generate. See ROS2_ON_PIP.md.
"""
import pathlib
import re
import sys
import sysconfig

import numpy


def main(venv: str) -> int:
    py_include = sysconfig.get_paths()["include"]
    np_include = numpy.get_include()
    py_pattern = re.compile(r"/opt/python/cp3\d+-cp3\d+/include/python3\.\d+")
    np_pattern = re.compile(r"/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+/site-packages/numpy/_core/include")
    changed = 0
    for path in pathlib.Path(venv, "share").rglob("*.cmake"):
        text = path.read_text(errors="surrogateescape")
        new = py_pattern.sub(py_include, np_pattern.sub(np_include, text))
        if new != text:
            path.write_text(new, errors="surrogateescape")
            changed += 1
    print(f"[setup] fixed include paths in {changed} CMake files", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
