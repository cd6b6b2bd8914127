"""specklewfs: focal-plane wavefront sensing with residual AO speckles (Codona &
Kenworthy 2013), Python bindings over libspecklewfs (ctypes, numpy).

Arrays follow the FITS order of the C library: C-contiguous numpy arrays of shape
(nframes, ny, nx) (x fastest); complex data are complex128. The library is found through
$SPECKLEWFS_LIB, else the path recorded at install time, else the build tree next to the
sources, else the dynamic loader. See docs/python.md.
"""
from ._lib import Error, LIBRARY_PATH
from .core import Geom, set_blas_threads, blas_threads, blas_kernel, aperture, zernike, wfe_compare, wfe_remove_ptt
from .fits import read_fits, write_fits, fits_info, read_keys, read_geom, read_geom_file
from .estimate import Accumulator, Halo, ACC_FIELDS, HALO_EXTS, G_SMOOTH_DEFAULT, phase_shift_map
from .pupil import PupilResult, pupil_estimate, pupil_files, choose_halo
from .telemetry import (Sparse, interp_ct_grid, actuators_hexapolar, actuators_square, actuators_read, actuators_write,
                        ShackHartmann,
                        dm_modes, slopes_remove_tiptilt, wind_from_slopes, slopes_noise_var, slopes_white_noise,
                        slopes_curl_noise,
                        vk_covariance, Recon, SpeckleModel, stack_lags, read_control,
                        schedule, make_schedule, speckles_expand, speckles_subtract_static, Engine, MFT)
from .coherence import (Coherence, coherence, default_lags, read_coherence_input, snr_factor, exposure_limit_wind,
                        bandwidth_radius)
from .sim import SimResult, simulate, sim_params, ncp_map, simulate_timeseries, mode_variance, mode_timecorr, demo, report
from .stream import Pipeline, Stream, FrameSync
from .realdata import (reduce, sync, boundary_check, boundary_gap, learn, meanmiss_metric, teach, modal_slopes, speckles,
                       estimate_files)
from .streamfiles import stream_files, sync_wfs_log
from .dm import DMFit, dm_offsets
from .live import StopFlag, live, replay, live_loop

try:
    from ._config import VERSION as __version__
except ImportError:
    __version__ = "0.11.0"

merge_files = Accumulator.merge_files


def _init_blas_threads():
    # The library's own workers (simulators, engine) run best with a single-threaded
    # OpenBLAS; a threaded one inside every small GEMM made the paper's simulation 5x
    # slower on 2 cores. The command line sets 1; so does the package at import, unless
    # the environment chooses: SPECKLEWFS_BLAS_THREADS=N (N <= 0 or 'keep': leave it), or
    # OPENBLAS_NUM_THREADS / OMP_NUM_THREADS set (then OpenBLAS already follows them).
    import os
    v = os.environ.get("SPECKLEWFS_BLAS_THREADS")
    if v is None:
        if os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS"):
            return
        v = "1"
    if v.strip().lower() == "keep":
        return
    try:
        n = int(v)
    except ValueError:
        raise ImportError(f"specklewfs: SPECKLEWFS_BLAS_THREADS must be an integer or 'keep', got {v!r}") from None
    if n > 0:
        set_blas_threads(n)


_init_blas_threads()


def _check_blas_kernel():
    # OpenBLAS chose its kernels when it was loaded, before this package could look. On a
    # CPU newer than the OpenBLAS build they are its generic ones (Debian 12's OpenBLAS on a
    # Xeon of model 207: SSE3 kernels on an AVX-512 CPU); the command line runs itself again
    # with OPENBLAS_CORETYPE set, which a Python process cannot do for itself: say so once.
    import os
    import warnings
    k = blas_kernel()
    if k["better"] and not os.environ.get("OPENBLAS_CORETYPE"):
        warnings.warn(f"specklewfs: OpenBLAS runs its {k['core']} kernels on this CPU, which runs {k['better']}'s "
                      f"(OpenBLAS does not know its model): set OPENBLAS_CORETYPE={k['better']} before starting "
                      "Python and teach, learn and pupil run 2-3 times as fast", RuntimeWarning, stacklevel=2)


_check_blas_kernel()
