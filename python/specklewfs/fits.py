"""Generic FITS input and output with the conventions of docs/conventions.md (fits.h): cubes are
(frame, y, x) numpy arrays, complex data use the FITS complex axis, geometry keywords
travel as a Geom."""
import ctypes

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, enc
from .core import Geom, geom_arg


class _In:
    def __init__(self, path, ext=None):
        self.f = ctypes.c_void_p()
        self.path = path
        check(lib.swfs_fits_in_open(ctypes.byref(self.f), enc(path), ext.encode() if ext else None),
              "swfs_fits_in_open")

    def __enter__(self):
        return self

    def __exit__(self, *a):
        lib.swfs_fits_in_close(self.f)
        self.f = None

    def shape(self):
        s = lib.swfs_fits_in_shape(self.f).contents
        return s

    def geom(self):
        g = _lib.swfs_geom()
        check(lib.swfs_fits_in_geom(self.f, ctypes.byref(g)), "swfs_fits_in_geom")
        return Geom.from_c(g)

    def key(self, name):
        """A keyword's value: a number (float) when it parses as one, else the string."""
        buf = ctypes.create_string_buffer(1024)
        found = ctypes.c_int()
        check(lib.swfs_fits_in_key_string_opt(self.f, name.encode(), buf, len(buf), ctypes.byref(found)),
              "swfs_fits_in_key_string_opt")
        if not found.value:
            return None
        s = buf.value.decode(errors="replace")
        if s.strip().upper() in ("T", "F"):
            return s.strip().upper() == "T"
        try:
            return float(s.replace("D", "E"))
        except ValueError:
            return s

    def read(self, squeeze=True):
        s = self.shape()
        if s.is_complex:
            p = ctypes.POINTER(_lib.swfs_cplx)()
            check(lib.swfs_fits_in_read_cplx_all(self.f, ctypes.byref(p)), "swfs_fits_in_read_cplx_all")
            return _lib.take_cplx(p, squeeze)
        p = ctypes.POINTER(_lib.swfs_real)()
        check(lib.swfs_fits_in_read_real_all(self.f, ctypes.byref(p)), "swfs_fits_in_read_real_all")
        return _lib.take_real(p, squeeze)


def read_fits(path, ext=None, squeeze=True):
    """(array, geom) of one image HDU (ext: EXTNAME, None: the first image). Real data come
    back as float64, complex (CTYPE1 = 'COMPLEX') as complex128; shape (nz, ny, nx), or
    (ny, nx) for a single plane when squeeze. The array is a view of the library's buffer
    (no copy)."""
    with _In(path, ext) as f:
        return f.read(squeeze), f.geom()


def fits_info(path, ext=None):
    """dict with nx, ny, nz, is_complex, bitpix of an image HDU."""
    with _In(path, ext) as f:
        s = f.shape()
        return {"nx": s.nx, "ny": s.ny, "nz": s.nz, "is_complex": bool(s.is_complex), "bitpix": s.bitpix}


def read_keys(path, keys, ext=None):
    """{key: value or None} from an HDU's header (falling back to the primary header):
    numbers as float, strings as str."""
    with _In(path, ext) as f:
        return {k: f.key(k) for k in keys}


def read_geom(path, ext=None):
    with _In(path, ext) as f:
        return f.geom()


def read_geom_file(path):
    """Geometry given in a file (the command line's --geom): a FITS file's header with the
    keywords, or KEY = VALUE lines; missing keys are NaN / 0 (fits.h, swfs_geom_read_file)."""
    g = _lib.swfs_geom()
    check(lib.swfs_geom_read_file(enc(path), ctypes.byref(g)), "swfs_geom_read_file")
    return Geom.from_c(g)


def write_fits(path, data, geom=None, provenance=(), bitpix=-64, keys=None):
    """Write arrays to a FITS file atomically (.part + rename).

    data: one array (written to the primary HDU) or a dict {EXTNAME: array} (image
    extensions after an empty primary), real or complex, 2-D (ny, nx) or 3-D (nz, ny, nx).
    geom, provenance (HISTORY lines) are stamped on every HDU; keys: {KEY: number or str}
    written on the last HDU."""
    items = [(None, data)] if not isinstance(data, dict) else list(data.items())
    out = ctypes.c_void_p()
    check(lib.swfs_fits_out_create(ctypes.byref(out), enc(path)), "swfs_fits_out_create")
    try:
        g = geom_arg(geom)
        prov, nprov = _lib.strings(provenance)
        check(lib.swfs_fits_out_set_stamp(out, ctypes.byref(g), prov, nprov), "swfs_fits_out_set_stamp")
        for name, a in items:
            arr = np.asarray(a)
            what = name or "data"
            ext = name.encode() if name else None
            if arr.dtype.kind == "c":
                arr = as_array(arr, what, np.complex128, ndim=(2, 3))
                s = _lib.cplx_struct(arr)
                check(lib.swfs_fits_out_cplx(out, ext, ctypes.byref(s), int(bitpix)), "swfs_fits_out_cplx")
            else:
                arr = as_array(arr, what, np.float64, ndim=(2, 3))
                s = _lib.real_struct(arr)
                check(lib.swfs_fits_out_real(out, ext, ctypes.byref(s), int(bitpix)), "swfs_fits_out_real")
        for k, v in (keys or {}).items():
            if isinstance(v, str):
                check(lib.swfs_fits_out_key_string(out, k.encode(), v.encode(), None), "swfs_fits_out_key_string")
            elif isinstance(v, (int, np.integer)) and not isinstance(v, bool):
                check(lib.swfs_fits_out_key_long(out, k.encode(), int(v), None), "swfs_fits_out_key_long")
            else:
                check(lib.swfs_fits_out_key_double(out, k.encode(), float(v), None), "swfs_fits_out_key_double")
    except BaseException:
        lib.swfs_fits_out_abort(out)
        raise
    check(lib.swfs_fits_out_commit(out), "swfs_fits_out_commit")
