"""The ctypes mirrors of the C structures match the headers: a C program prints the size
and every field offset of each mirrored structure, compared with ctypes."""
import ctypes
import os
import shutil
import subprocess

import pytest

from specklewfs import _lib

from conftest import ROOT

HEADERS = ["accum", "checkpoint", "coherence", "engine", "estimate", "fits", "geom", "pupil", "recovery", "sim",
           "sparse", "speckles", "timeseries", "wfs", "array", "pipeline", "stream", "lmodel", "reduce", "sync", "run",
           "parallel", "framesync", "report", "shm", "live"]


def test_struct_layout(tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    if not cc:
        pytest.skip("no C compiler")
    lines = [f'#include "specklewfs/{h}.h"' for h in HEADERS] + ["#include <stdio.h>", "#include <stddef.h>",
                                                                  "int main(void) {"]
    expected = []
    for s in _lib.STRUCTS:
        lines.append(f'printf("{s._cname_} sizeof %zu\\n", sizeof({s._cname_}));')
        expected.append(f"{s._cname_} sizeof {ctypes.sizeof(s)}")
        for name, _t in s._fields_:
            lines.append(f'printf("{s._cname_} {name} %zu\\n", offsetof({s._cname_}, {name}));')
            expected.append(f"{s._cname_} {name} {getattr(s, name).offset}")
    lines += ["return 0; }"]
    src = tmp_path / "layout.c"
    src.write_text("\n".join(lines) + "\n")
    exe = tmp_path / "layout"
    subprocess.run([cc, "-std=c11", "-I", os.path.join(ROOT, "include"), str(src), "-o", str(exe)], check=True)
    got = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split("\n")[:-1]
    assert got == expected
    # The numpy schedule dtype is swfs_exposure.
    assert _lib.EXPOSURE_DTYPE.itemsize == ctypes.sizeof(_lib.swfs_exposure)
    assert [_lib.EXPOSURE_DTYPE.fields[n][1] for n in ("first", "count", "w_first", "w_last")] == \
        [getattr(_lib.swfs_exposure, n).offset for n in ("first", "count", "w_first", "w_last")]
