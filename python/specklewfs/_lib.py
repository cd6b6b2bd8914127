"""Loading libspecklewfs, the C structures mirrored with ctypes, function prototypes,
error handling and the numpy <-> C array helpers.

Internal: the public API is in the other modules. The mirrored structures must match
include/specklewfs/*.h field for field; python/tests/test_layout.py compiles a C program
that prints every offset and size and compares them with these classes.
"""
import ctypes
import ctypes.util
import os

import numpy as np

c_size = ctypes.c_size_t
c_dbl = ctypes.c_double
c_int = ctypes.c_int
c_long = ctypes.c_long
c_u64 = ctypes.c_uint64
c_ptr = ctypes.c_void_p
c_str = ctypes.c_char_p
P = ctypes.POINTER


# ---- locating the library ------------------------------------------------------------

def _candidates():
    env = os.environ.get("SPECKLEWFS_LIB")
    if env:
        return [("SPECKLEWFS_LIB", env)]
    out = []
    try:
        from . import _config  # written by CMake at install time
        out.append(("installed", _config.LIBRARY))
    except ImportError:
        pass
    here = os.path.dirname(os.path.abspath(__file__))
    build = os.path.normpath(os.path.join(here, "..", "..", "build", "libspecklewfs.so"))
    out.append(("build tree", build))
    found = ctypes.util.find_library("specklewfs")
    if found:
        out.append(("find_library", found))
    return out


def _load():
    tried = []
    for how, path in _candidates():
        # find_library returns a bare soname: let the dynamic loader search for it.
        if os.sep in path and not os.path.exists(path):
            tried.append(f"{how}: {path} (no such file)")
            continue
        try:
            return ctypes.CDLL(path), (os.path.abspath(path) if os.sep in path else path)
        except OSError as e:
            tried.append(f"{how}: {path} ({e})")
    raise ImportError("specklewfs: cannot load libspecklewfs.so; set SPECKLEWFS_LIB to its path. Tried: "
                      + "; ".join(tried or ["nothing"]))


lib, LIBRARY_PATH = _load()


# ---- errors ----------------------------------------------------------------------------

STATUS_NAMES = ["SWFS_OK", "SWFS_ERR_ARG", "SWFS_ERR_NOMEM", "SWFS_ERR_IO", "SWFS_ERR_FORMAT", "SWFS_ERR_SHAPE",
                "SWFS_ERR_VALUE", "SWFS_ERR_NUMERIC", "SWFS_ERR_INTERNAL", "SWFS_ERR_STOPPED"]  # enum swfs_status (status.h)
SWFS_ERR_STOPPED = STATUS_NAMES.index("SWFS_ERR_STOPPED")
SWFS_ERR_INTERNAL = STATUS_NAMES.index("SWFS_ERR_INTERNAL")


class Error(RuntimeError):
    """A library call failed. `status` is the swfs_status code, `status_name` its enum
    name (e.g. 'SWFS_ERR_IO'), `description` the library's short description of it
    (swfs_status_name), `message` the library's message (swfs_last_error) and
    `function` the C function that failed."""

    def __init__(self, status, message, function):
        self.status = int(status)
        self.status_name = STATUS_NAMES[self.status] if 0 <= self.status < len(STATUS_NAMES) else str(self.status)
        self.description = lib.swfs_status_name(self.status).decode()
        self.message = message
        self.function = function
        super().__init__(f"{message} [{self.status_name}: {self.description}, from {function}]")


def _last_error():
    m = lib.swfs_last_error()
    return m.decode(errors="replace") if m else "(no message)"


def check(rc, function):
    """Raise Error if rc is not SWFS_OK. Call right after the C call: the message is
    thread-local and the next call may overwrite it."""
    if rc != 0:
        raise Error(rc, _last_error(), function)


def check_ptr(p, function, status=None):
    if not p:
        # Functions that return NULL give no status; SWFS_ERR_ARG unless told otherwise.
        raise Error(status if status is not None else 1, _last_error(), function)
    return p


# ---- structures ----------------------------------------------------------------------

class Struct(ctypes.Structure):
    _cname_ = None  # the C type, for the layout test


def _s(cname, fields):
    return type(cname, (Struct,), {"_fields_": fields, "_cname_": cname})


swfs_real = _s("swfs_real", [("nx", c_size), ("ny", c_size), ("nz", c_size), ("data", P(c_dbl))])
swfs_cplx = _s("swfs_cplx", [("nx", c_size), ("ny", c_size), ("nz", c_size), ("data", c_ptr)])
swfs_geom = _s("swfs_geom", [("wavelen", c_dbl), ("teldiam", c_dbl), ("obscur", c_dbl), ("pixscale", c_dbl),
                             ("pupdx", c_dbl), ("pupn", c_long)])
swfs_blas_kernel_info = _s("swfs_blas_kernel_info", [("core", ctypes.c_char * 32), ("better", ctypes.c_char * 16),
                                                    ("fallback", ctypes.c_char * 32)])
swfs_noise = _s("swfs_noise", [("read_noise", c_dbl), ("gain", c_dbl)])
HALO_REAL = ["gain", "gain_pix", "visib", "snr", "mean_i", "var_i", "mean_sp", "var_sp", "stab_err", "circ",
             "valid", "nframes"]
HALO_CPLX = ["halo", "halo_lf", "stab"]
swfs_halo = _s("swfs_halo", [("nx", c_size), ("ny", c_size)] + [(n, P(swfs_cplx)) for n in HALO_CPLX]
               + [(n, P(swfs_real)) for n in HALO_REAL]
               + [(n, c_size) for n in ("npix", "n_valid", "n_bad_radicand", "n_no_speckle", "n_no_frames")]
               + [(n, c_dbl) for n in ("valid_fraction", "median_snr", "radicand_min")]
               + [("frames", ctypes.c_ulonglong), ("skipped", ctypes.c_ulonglong), ("noise", swfs_noise),
                  ("g_smooth", c_dbl), ("n_g_fallback", c_size), ("n_var_below_noise", c_size),
                  ("reg", c_ptr), ("resmean", P(swfs_real)), ("tiptilt", ctypes.c_char * 16)])
swfs_estimate_options = _s("swfs_estimate_options", [("g_smooth", c_dbl)])
ACC_NFIELDS = 15
ACC_FIELDS = ["N", "MI", "MX", "MY", "MA", "CII", "CIX", "CIY", "CIA", "CXX", "CXY", "CXA", "CYY", "CYA", "CAA"]
swfs_accum = _s("swfs_accum", [("nx", c_size), ("ny", c_size), ("f", P(c_dbl) * ACC_NFIELDS), ("frames", c_u64),
                               ("skipped", c_u64), ("reg", c_ptr)])
swfs_jointfit_options = _s("swfs_jointfit_options", [
    ("knot_factor", c_dbl), ("legendre_order", c_int), ("g_prior_sigma", c_dbl), ("fit_kappa", c_int),
    ("max_iter", c_int), ("gls_iter", c_int), ("tol", c_dbl), ("lambda_phi", c_dbl), ("lambda_alpha", c_dbl),
    ("alpha_ratio", c_dbl), ("alpha_ratio_max", c_dbl), ("prior", c_int), ("intercept", c_int),
    ("threads", c_int), ("g_radial", c_dbl)])
swfs_jointfit_result = _s("swfs_jointfit_result", [
    ("field", P(swfs_cplx)), ("wfe", P(swfs_real)), ("mask", P(swfs_real)), ("halo", P(swfs_cplx)),
    ("gain", P(swfs_real)), ("kappa", c_dbl), ("lambda_phi", c_dbl), ("lambda_alpha", c_dbl), ("gamma_phi", c_dbl),
    ("gamma_alpha", c_dbl), ("chi2", c_dbl), ("cost", c_dbl), ("npix", c_size), ("nintervals", c_size),
    ("nbasis", c_size), ("nparams", c_size), ("iterations", c_int), ("evaluations", c_int), ("seconds", c_dbl),
    ("wfe_rms", c_dbl), ("intercept", c_int), ("delta_chi2", c_dbl), ("delta_chi2_limit", c_dbl),
    ("noise_scale", c_dbl), ("model_stopped", c_int), ("warm_start", c_int), ("log_evidence", c_dbl),
    ("log_evidence_alt", c_dbl)])
swfs_pupil_options = _s("swfs_pupil_options", [("weight", c_int), ("wiener_k", c_dbl), ("bias", c_dbl),
                                               ("source", c_int), ("method", c_int),
                                               ("fit", swfs_jointfit_options), ("keep_resmean", c_int)])
swfs_pupil_result = _s("swfs_pupil_result", [("field", P(swfs_cplx)), ("wfe", P(swfs_real)),
                                             ("surface", P(swfs_real)), ("amplitude", P(swfs_real)),
                                             ("mask", P(swfs_real)), ("wfe_rms", c_dbl), ("wfe_pv", c_dbl),
                                             ("strehl", c_dbl), ("opt", swfs_pupil_options), ("method", c_int),
                                             ("fit", P(swfs_jointfit_result)), ("explained", c_dbl),
                                             ("explained_median", c_dbl), ("explained_map", P(swfs_real)),
                                             ("resmean", P(swfs_real)), ("resmean_rms", c_dbl)])
swfs_sparse = _s("swfs_sparse", [("nrows", c_size), ("ncols", c_size), ("nnz", c_size), ("row_ptr", P(c_size)),
                                 ("col", P(c_size)), ("val", P(c_dbl))])
swfs_dm_registration = _s("swfs_dm_registration", [("pitch", c_dbl), ("x0", c_dbl), ("y0", c_dbl), ("rot", c_dbl),
                                                   ("flip_x", c_int)])
swfs_linear_input = _s("swfs_linear_input", [("nmeas", c_size), ("basis", P(swfs_sparse)), ("control", P(c_dbl)),
                                             ("imat", P(c_dbl)), ("scale", c_dbl), ("shapes", P(c_dbl)),
                                             ("nshapes", c_size), ("nlags", c_size)])
swfs_shwfs = _s("swfs_shwfs", [("nsub", c_size), ("nslopes", c_size), ("npup", c_size), ("pupdx", c_dbl),
                               ("diam", c_dbl), ("S", P(swfs_sparse)), ("valid", P(ctypes.c_ubyte)),
                               ("nvalid", c_size)])
RECON_MAXLAGS = 16  # SWFS_RECON_MAXLAGS (wfs.h): a space-time reconstructor's lags at most
LEARN_MAXWLAYERS = 8  # SWFS_LEARN_MAXWLAYERS (run.h): the training loops' layer groups at most
swfs_recon = _s("swfs_recon", [("nact", c_size), ("nslopes", c_size), ("W", P(c_dbl)), ("nmodes", c_size),
                               ("sv", P(c_dbl)), ("nsv", c_size), ("noise_var", c_dbl), ("dof", c_dbl),
                               ("l0", c_dbl), ("prior_scale", c_dbl), ("nlags", c_size),
                               ("lags", ctypes.c_long * RECON_MAXLAGS), ("oxy", P(c_dbl))])
swfs_speckle_model = _s("swfs_speckle_model", [("npup", c_size), ("nact", c_size), ("nslopes", c_size),
                                               ("pupdx", c_dbl), ("mask", P(c_dbl)), ("T", P(swfs_sparse)),
                                               ("wfs", P(swfs_shwfs)), ("recon", P(swfs_recon)),
                                               ("n_outside", c_size)])
swfs_engine_config = _s("swfs_engine_config", [("nslopes", c_size), ("nact", c_size), ("npup", c_size),
                                               ("nfx", c_size), ("nfy", c_size), ("alpha", c_dbl),
                                               ("wavelen", c_dbl), ("recon", P(c_dbl)),
                                               ("interp", P(swfs_sparse)), ("pupil", P(c_dbl)),
                                               ("remove_tiptilt", c_int), ("nthreads", c_int)])
swfs_exposure = _s("swfs_exposure", [("first", c_size), ("count", c_size), ("w_first", c_dbl), ("w_last", c_dbl)])
# The same layout as a numpy dtype, so schedules pass to C without copies.
EXPOSURE_DTYPE = np.dtype([("first", np.uintp), ("count", np.uintp), ("w_first", np.float64),
                           ("w_last", np.float64)], align=True)
swfs_coh_options = _s("swfs_coh_options", [("lags", P(c_long)), ("nlags", c_size), ("max_lag", c_long),
                                           ("nfit", c_int), ("exposure", c_dbl), ("min_power_rel", c_dbl),
                                           ("method", c_int)])
swfs_coherence = _s("swfs_coherence", [("nx", c_size), ("ny", c_size), ("nframes", c_size), ("framedt", c_dbl),
                                       ("nlags", c_size), ("lag_frames", P(c_long)), ("lags", P(swfs_real)),
                                       ("mean_sp", P(swfs_real)), ("tau0", P(swfs_real)), ("trot", P(swfs_real)),
                                       ("phrate", P(swfs_real)), ("snr_fact", P(swfs_real)),
                                       ("mcf", P(swfs_cplx)), ("exposure", c_dbl), ("max_lag", c_long),
                                       ("dense", c_ptr), ("nfit", c_int), ("method", c_int), ("n_valid", c_size),
                                       ("n_nopower", c_size), ("n_nonfinite", c_size),
                                       ("n_tau0_beyond", c_size)])
swfs_screen_params = _s("swfs_screen_params", [("n", c_size), ("dx", c_dbl), ("r0", c_dbl), ("L0", c_dbl),
                                               ("subharmonics", c_int)])
WIND_MAXLAGS = 32
WIND_MAXLAYERS = 4
swfs_wind_layer = _s("swfs_wind_layer", [("vx", c_dbl), ("vy", c_dbl), ("speed", c_dbl), ("direction", c_dbl),
                                         ("corr", c_dbl), ("signif", c_dbl), ("nlags", c_size)])
swfs_wind_lag = _s("swfs_wind_lag", [("lag", c_size), ("dx", c_dbl), ("dy", c_dbl), ("corr", c_dbl), ("inside", c_int),
                                     ("used", c_int)])
swfs_wind_estimate = _s("swfs_wind_estimate", [
    ("found", c_int), ("vx", c_dbl), ("vy", c_dbl), ("speed", c_dbl), ("direction", c_dbl), ("nused", c_size),
    ("nlags", c_size), ("lag", swfs_wind_lag * WIND_MAXLAGS), ("nvalid", c_size), ("radius", c_size),
    ("nlayers", c_size), ("layer", swfs_wind_layer * WIND_MAXLAYERS), ("threshold", c_dbl), ("next_signif", c_dbl),
    ("nstack", c_size), ("tracked_signif", c_dbl), ("tracked_dropped", c_int)])
SIM_MAX_ZERNIKE = 64
swfs_sim_params = _s("swfs_sim_params", [
    ("screen", swfs_screen_params), ("nscreens", c_int), ("teldiam", c_dbl), ("pupn", c_long), ("pupdx", c_dbl),
    ("obscur", c_dbl), ("nspiders", c_int), ("spider_width", c_dbl), ("wavelen", c_dbl), ("spacing", c_dbl),
    ("per_screen", c_long), ("target_rms", c_dbl), ("lag_shift", c_dbl), ("lag_angle", c_dbl), ("nfx", c_long),
    ("nfy", c_long), ("pixscale", c_dbl), ("total_counts", c_dbl), ("read_noise", c_dbl), ("gain", c_dbl),
    ("ncp_trefoil", c_dbl), ("ncp_gauss_depth", c_dbl), ("ncp_gauss_radius", c_dbl), ("ncp_gauss_x", c_dbl),
    ("ncp_gauss_y", c_dbl), ("ncp_zernike", c_dbl * (3 * SIM_MAX_ZERNIKE)), ("ncp_nzernike", c_size),
    ("ncp_map", ctypes.c_char * 1024), ("pupil_mask", ctypes.c_char * 1024), ("seed", c_u64), ("threads", c_int)])
SIM_RESULT_SCALARS = ["counts_scale", "field_scale", "residual_rms", "expected_rms", "lag_floor_rms",
                      "kernel_sigma", "strehl", "strehl_ao", "window_fraction", "ncp_rms", "ncp_pv", "seconds"]
swfs_sim_result = _s("swfs_sim_result", [
    ("params", swfs_sim_params), ("geom", swfs_geom), ("nframes", c_size), ("per_screen", c_size),
    ("science", P(swfs_real)), ("speckles", P(swfs_cplx)), ("speckle_mean", P(swfs_cplx)), ("ncp", P(swfs_real)),
    ("halo_true", P(swfs_cplx)), ("pupil", P(swfs_real)), ("ref_phase", P(c_dbl))]
    + [(n, c_dbl) for n in SIM_RESULT_SCALARS])
RECOVERY_FIELDS = ["sigma", "valid_fraction", "bad_radicand", "median_snr", "err_paper", "err_halo", "err_lf",
                   "err_lf_snr", "wfe_rms", "wfe_pv", "strehl", "err_fit", "fit_kappa"]
swfs_recovery = _s("swfs_recovery", [(n, c_dbl) for n in RECOVERY_FIELDS])
TS_MAX_LAYERS = 3
swfs_ts_params = _s("swfs_ts_params", [
    ("base", swfs_sim_params), ("nlayers", c_int), ("layer_frac", c_dbl * TS_MAX_LAYERS),
    ("layer_speed", c_dbl * TS_MAX_LAYERS), ("layer_dir", c_dbl * TS_MAX_LAYERS), ("wfs_rate", c_dbl),
    ("nsub", c_long), ("act_pitch", c_dbl), ("ao_gain", c_dbl), ("ao_delay", c_long), ("ao_modes", c_long),
    ("ao_rcond", c_dbl), ("slope_noise", c_dbl), ("wfs_pyramid", c_long), ("pyr_mod", c_dbl), ("pyr_nmod", c_long), ("wfs_wavelen", c_dbl),
    ("pyr_photons", c_dbl), ("vib_amp", c_dbl), ("vib_freq", c_dbl), ("vib_angle", c_dbl), ("jitter_amp", c_dbl),
    ("jitter_freq", c_dbl), ("frame_ratio", c_dbl), ("ncubes", c_long), ("cube_frames", c_long),
    ("cube_gap", c_dbl), ("start_offset", c_dbl), ("handshake_lag", c_long), ("wfs_file_frames", c_long),
    ("bandwidth", c_dbl), ("nlambda", c_long), ("background", c_dbl), ("dark_level", c_dbl), ("flat_rms", c_dbl),
    ("nhot", c_long), ("ndead", c_long), ("camera_swap", c_long), ("camera_flip_x", c_long),
    ("camera_flip_y", c_long), ("act_square", c_long), ("dm_coupling", c_dbl), ("export_modal", c_long), ("export_truth", c_long),
    ("camera_light", c_long), ("milk", c_long), ("milk_epoch", c_dbl),
    ("milk_jitter", c_dbl), ("milk_drift", c_dbl), ("milk_offset", c_dbl), ("milk_drop_wfs", c_long),
    ("milk_drop_cam", c_long), ("milk_file_frames", c_long), ("milk_cam_file_frames", c_long),
    ("actuators", ctypes.c_char * 1024), ("ao_recon", ctypes.c_char * 1024), ("valid", ctypes.c_char * 1024),
    ("truth_actuators", ctypes.c_char * 1024)])
TS_SUMMARY_FIELDS = [("nwfs", c_size), ("nact", c_size), ("nvalid", c_size), ("ao_modes", c_size),
                     ("residual_rms", c_dbl), ("residual_rms_nott", c_dbl), ("tt_rms", c_dbl), ("strehl", c_dbl),
                     ("static_rms", c_dbl), ("ncp_rms", c_dbl), ("seconds", c_dbl)]
swfs_ts_summary = _s("swfs_ts_summary", TS_SUMMARY_FIELDS)
swfs_pipeline_options = _s("swfs_pipeline_options", [("recon", c_int), ("rcond", c_dbl), ("max_modes", c_size),
                                                     ("slope_noise", c_dbl), ("vk_l0", c_dbl), ("tiptilt", c_int),
                                                     ("threads", c_int), ("wfs_rate", c_int), ("recon_scale", c_dbl),
                                                     ("valid", c_ptr), ("valid_nsub", c_size), ("band", c_dbl)])
PIPELINE_INFO_FIELDS = [("nact", c_size), ("nslopes", c_size), ("npup", c_size), ("nfx", c_size), ("nfy", c_size),
                        ("recon_modes", c_size), ("recon_dof", c_dbl), ("noise_var", c_dbl), ("noise_given", c_int),
                        ("ntrain", c_size), ("n_outside", c_size), ("vk_l0", c_dbl), ("recon_gain", c_dbl),
                        ("nbasis", c_size), ("basis_nnz", c_size), ("composed", c_int), ("resid_rms", c_dbl),
                        ("nsub", c_size), ("nvalid", c_size), ("band", c_dbl), ("band_out", c_size),
                        ("nlags", c_size), ("out_pitch", c_dbl), ("imat_rank", c_size)]
swfs_pipeline_info = _s("swfs_pipeline_info", PIPELINE_INFO_FIELDS)
swfs_batch = _s("swfs_batch", [("slopes", P(c_dbl)), ("nwfs", c_size), ("sched", c_ptr), ("science", P(c_dbl)),
                               ("nexp", c_size), ("cube", c_size)])
swfs_stream_options = _s("swfs_stream_options", [("static_mode", c_int), ("static_halo", c_ptr),
                                                 ("noise", swfs_noise), ("est", swfs_estimate_options),
                                                 ("every", c_size), ("every_seconds", c_dbl),
                                                 ("max_frames", c_size)])
swfs_framesync_options = _s("swfs_framesync_options", [("batch", c_size), ("max_wait", c_dbl), ("exptime", c_dbl),
                                                       ("clock_memory", c_dbl), ("wfs_history", c_size),
                                                       ("camera_queue", c_size), ("lags", P(c_long)), ("nlags", c_size)])
FRAMESYNC_COUNTS = ["wfs_received", "camera_received", "wfs_dropped", "camera_dropped", "wfs_restarts",
                    "camera_restarts", "wfs_segments", "camera_segments", "used", "incomplete", "no_wfs", "unsettled",
                    "overrun", "wfs_bad", "wfs_late", "batches"]
swfs_framesync_stats = _s("swfs_framesync_stats", [(n, c_u64) for n in FRAMESYNC_COUNTS] +
                          [("wfs_period", c_dbl), ("camera_period", c_dbl)])
swfs_fits_shape = _s("swfs_fits_shape", [("nx", c_size), ("ny", c_size), ("nz", c_size), ("is_complex", c_int),
                                         ("bitpix", c_int)])

PROGRESS_FN = ctypes.CFUNCTYPE(c_int, c_ptr, c_str, c_size, c_size)  # status.h: non-zero stops the run

# run.h, reduce.h, sync.h: the real-data path's file-level steps (realdata.py)
swfs_linear_files = _s("swfs_linear_files", [("basis", c_str), ("control", c_str), ("imat", c_str),
                                             ("reg", swfs_dm_registration), ("scale", c_dbl)])
swfs_reduce_params = _s("swfs_reduce_params", [("hot_sigma", c_dbl), ("flat_min", c_dbl), ("flat_max", c_dbl),
                                               ("gauss_sigma", c_dbl), ("do_register", c_int), ("bg_radius", c_dbl),
                                               ("pixscale", c_dbl), ("gain", c_dbl)])
swfs_reduce_run_options = _s("swfs_reduce_run_options", [
    ("raw", P(c_str)), ("nraw", c_size), ("dark", c_str), ("flat", c_str), ("badpix", c_str), ("out", c_str),
    ("params", swfs_reduce_params), ("sigma_given", c_int), ("noise_region", c_int), ("prov", P(c_str)),
    ("nprov", c_size), ("progress", PROGRESS_FN), ("progress_ctx", c_ptr), ("geom", swfs_geom)])
REDUCE_RESULT_FIELDS = [("nframes", c_size), ("nbad", c_size), ("noise_var", c_dbl), ("noise_fac", c_dbl),
                        ("noise_var_measured", c_dbl), ("missing", ctypes.c_char * 96), ("overridden", c_int),
                        ("stamped", c_int), ("dropped", c_u64), ("exptime", c_dbl)]
swfs_reduce_run_result = _s("swfs_reduce_run_result", REDUCE_RESULT_FIELDS)
swfs_sync_params = _s("swfs_sync_params", [("ratio_min", c_dbl), ("ratio_max", c_dbl), ("lag_min", c_dbl),
                                           ("lag_max", c_dbl), ("ratio_step", c_dbl), ("lag_step", c_dbl)])
SYNC_RESULT_FIELDS = [("ratio", c_dbl), ("ratio_err", c_dbl), ("lag", c_dbl), ("swap", c_int), ("sign_x", c_int),
                      ("sign_y", c_int), ("corr_x", c_dbl), ("corr_y", c_dbl), ("corr4", c_dbl * 4),
                      ("ncubes_used", c_size), ("neff", c_dbl), ("nexp", c_size), ("z", c_dbl), ("z_need", c_dbl),
                      ("lag_min", c_dbl), ("lag_max", c_dbl), ("lag_moves", c_int)]
swfs_sync_result = _s("swfs_sync_result", SYNC_RESULT_FIELDS)
swfs_sync_boundary = _s("swfs_sync_boundary", [("verdict", c_int), ("q", c_dbl), ("q1_max", c_dbl),
                                               ("q2_min", c_dbl), ("n1", c_size), ("n2", c_size),
                                               ("window", c_size), ("q_window", c_dbl), ("p_lost", c_dbl),
                                               ("p_contiguous", c_dbl)])
swfs_sync_gap = _s("swfs_sync_gap", [("lost", c_long), ("consistent", c_int), ("separable", c_int), ("q", c_dbl),
                                     ("qk_min", c_dbl), ("qk_max", c_dbl), ("qfar_min", c_dbl)])
SYNC_EDGE_FRAMES = 128  # SWFS_SYNC_EDGE_FRAMES (sync.h)
swfs_timing = _s("swfs_timing", [("ratio", c_dbl), ("ratio_err", c_dbl), ("lag", c_dbl), ("fit", swfs_sync_result),
                                 ("ncubes", c_size), ("cubes", c_ptr)])
swfs_sync_run_options = _s("swfs_sync_run_options", [("science", c_str), ("handshake", c_str), ("out", c_str),
                                                     ("params", swfs_sync_params), ("lin", swfs_linear_files)])
SYNC_RUN_FIELDS = [("nok", c_size), ("nexp", c_size), ("nexp_ok", c_size), ("ncontinued", c_size),
                   ("ratio_min", c_dbl), ("ratio_max", c_dbl), ("ratio_bound", c_dbl), ("ratio_auto", c_int),
                   ("refits", c_int), ("ratio_first", c_dbl), ("lag_first", c_dbl), ("nmissing", c_size),
                   ("nexp_missing", c_size), ("missing_reason", ctypes.c_char * 1024), ("exptime_ratio", c_dbl),
                   ("exptime_used", c_int), ("exptime_widened", c_int)]
swfs_sync_run_result = _s("swfs_sync_run_result", [("t", swfs_timing)] + SYNC_RUN_FIELDS)
swfs_learn_run_options = _s("swfs_learn_run_options", [
    ("dirs", P(c_str)), ("ndirs", c_size), ("ridge", c_dbl), ("out", c_str), ("modal", c_int), ("no_heldout", c_int),
    ("heldout_ratio", P(c_dbl)), ("prov", P(c_str)), ("nprov", c_size), ("progress", PROGRESS_FN), ("progress_ctx", c_ptr),
    ("lags", P(ctypes.c_long)), ("nlags", c_size), ("perframe_out", c_str), ("curve", c_int),
    ("curve_radius", c_dbl * 2), ("project", P(c_dbl)), ("nproject", c_size), ("threads", c_int), ("mean_miss", c_int),
    ("prior", c_str), ("mean_miss_heldout", c_int), ("meanmiss_metric", P(c_dbl)),
    ("meanmiss_metric_n", c_size)])
swfs_recon_learn_info = _s("swfs_recon_learn_info", [("nframes", c_size), ("nslopes_seen", c_size),
                                                     ("truth_rms", c_dbl), ("misfit_rms", c_dbl)])
swfs_learn_run_result = _s("swfs_learn_run_result", [
    ("info", swfs_recon_learn_info), ("nfiles", c_size), ("nslopes", c_size), ("nact", c_size), ("nheldout", c_size),
    ("heldout_misfit_rms", c_dbl), ("heldout_truth_rms", c_dbl), ("heldout_worst", c_dbl),
    ("heldout_worst_set", c_size), ("nwind", c_size), ("wind_vx", c_dbl), ("wind_vy", c_dbl), ("wind_spread", c_dbl),
    ("nwlayers", c_size), ("wlayer_vx", c_dbl * LEARN_MAXWLAYERS), ("wlayer_vy", c_dbl * LEARN_MAXWLAYERS),
    ("wlayer_spread", c_dbl * LEARN_MAXWLAYERS), ("wlayer_n", c_size * LEARN_MAXWLAYERS),
    ("corr", c_dbl * RECON_MAXLAGS), ("corr_spread", c_dbl * RECON_MAXLAGS),
    ("perframe_info", swfs_recon_learn_info), ("curve_n", c_size * 2), ("curve_m2", c_dbl * 2), ("curve_s2", c_dbl * 2),
    ("curve_a", c_dbl),
    ("curve_b", c_dbl), ("curve_excess", c_dbl), ("curve_frames", c_size), ("curve_outputs", c_size),
    ("meanmiss_heldout", c_dbl), ("meanmiss_rms", c_dbl), ("meanmiss_set_rms", c_dbl), ("meanmiss_kept", c_int),
    ("heldout_outputs", c_size), ("heldout_scaled_rms", c_dbl), ("curve_fall_se", c_dbl)])
swfs_speckles_run_options = _s("swfs_speckles_run_options", [
    ("timing", c_str), ("science", c_str), ("actuators", c_str), ("out", c_str), ("recon", c_str), ("mask", c_str),
    ("write_recon", c_str), ("pipe", swfs_pipeline_options), ("mean_mode", c_int), ("wfs_hz", c_dbl),
    ("match_in", P(c_str)), ("match_out", P(c_str)), ("nmatch", c_size), ("prov", P(c_str)), ("nprov", c_size),
    ("progress", PROGRESS_FN), ("progress_ctx", c_ptr), ("batch", c_size), ("team", c_ptr), ("geom", swfs_geom),
    ("lin", swfs_linear_files), ("valid", c_str), ("teach_work", c_str), ("teach_loops", c_size), ("teach_max_loops", c_size),
    ("teach_seed", c_u64),
    ("teach_keep_loops", c_int), ("teach", c_ptr), ("teach_again", c_int), ("teach_keys", P(c_str)),
    ("nteach_keys", c_size), ("mean_loops", P(c_str)), ("nmean_loops", c_size), ("mean_teach", c_int),
    ("mean_teach_loops", c_size), ("loops_map", c_int), ("resmean_from", c_str), ("mean_teach_max_loops", c_size),
    ("mean_rec_out", c_str), ("pairing_table", c_int)])
RECON_TEACH = 4  # run.h SWFS_RECON_TEACH: speckles' default
MEAN_TEACH_MAX = 16  # run.h SWFS_MEAN_TEACH_MAX
swfs_loops_map_result = _s("swfs_loops_map_result", [
    ("tried", c_int), ("chosen", c_int), ("explained", c_dbl * 2), ("ncommon", c_size), ("nframes", c_size),
    ("inputs", c_size), ("misfit_rms", c_dbl), ("truth_rms", c_dbl), ("carry_resid", c_dbl),
    ("meanmiss_heldout", c_dbl), ("meanmiss_rms", c_dbl), ("mean_from_imat", c_int), ("seconds", c_dbl),
    ("work", ctypes.c_char * 4200), ("map", ctypes.c_char * 4400), ("fallback", ctypes.c_char * 1024),
    ("mix_weight", c_dbl * 3), ("explained_mix", c_dbl * 3), ("weight", c_dbl), ("mix_note", ctypes.c_char * 1024),
    ("nlags", c_size), ("lags", ctypes.c_long * RECON_MAXLAGS), ("lag_speed", c_dbl), ("st_frames", c_size),
    ("pf_meanmiss_heldout", c_dbl), ("mean_from_perframe", c_int)])
LOOPS_MAP_NMIX = 3  # run.h SWFS_LOOPS_MAP_NMIX
swfs_mean_teach_result = _s("swfs_mean_teach_result", [
    ("done", c_int), ("reused", c_int), ("automatic", c_int), ("fallback", ctypes.c_char * 1024), ("nloops", c_size), ("loop_frames", c_size), ("pyramid", c_int),
    ("noise_rms", c_dbl), ("photons", c_dbl), ("slope_noise", c_dbl), ("knee", c_size), ("nlayers", c_size),
    ("speed", c_dbl * WIND_MAXLAYERS), ("direction", c_dbl * WIND_MAXLAYERS), ("act_pitch", c_dbl),
    ("r0", c_dbl), ("r0_pairs", c_size), ("power", c_dbl), ("power_ratio", c_dbl),
    ("nloops_first", c_size), ("curve_excess", c_dbl), ("curve_frames", c_size),
    ("seconds", c_dbl), ("work", ctypes.c_char * 4200)])
swfs_milk_source_stats = _s("swfs_milk_source_stats", [("sync", swfs_framesync_stats), ("wfs_dropped_log", c_u64),
                                                       ("camera_dropped_log", c_u64), ("exptime", c_dbl)])
swfs_stream_run_options = _s("swfs_stream_run_options", [
    ("timing", c_str), ("science", c_str), ("slopes", c_str), ("recon", c_str), ("actuators", c_str), ("out", c_str),
    ("pupil_out", c_str), ("pupil_method", c_int), ("checkpoint", c_str), ("static_file", c_str),
    ("static_out", c_str), ("mask", c_str), ("tiptilt", c_int), ("threads", c_int), ("batch", c_size),
    ("read_noise", c_dbl), ("gain", c_dbl), ("g_smooth_lod", c_dbl), ("stream", swfs_stream_options),
    ("prov", P(c_str)), ("nprov", c_size), ("on_update", c_ptr), ("update_ctx", c_ptr), ("team", c_ptr),
    ("pupil_source", c_int), ("geom", swfs_geom), ("lin", swfs_linear_files), ("wfs_logs", P(c_str)),
    ("nwfs_logs", c_size), ("clock", c_str), ("exptime", c_dbl), ("valid", c_str), ("band", c_dbl),
    ("mean_loops", P(c_str)), ("nmean_loops", c_size), ("mean_teach", c_int), ("mean_teach_loops", c_size),
    ("teach_work", c_str), ("teach_again", c_int), ("mean_teach_max_loops", c_size), ("progress", PROGRESS_FN),
    ("progress_ctx", c_ptr)])
swfs_stream_run_result = _s("swfs_stream_run_result", [
    ("camera_frames", c_size), ("wfs_frames", c_dbl), ("seconds", c_dbl), ("wfs_rate", c_dbl),
    ("static_scale", c_dbl), ("ratio", c_dbl), ("noise", swfs_noise), ("info", swfs_pipeline_info),
    ("stamped", c_int), ("stamps", swfs_milk_source_stats), ("st_lags", c_long * RECON_MAXLAGS),
    ("st_edges_joined", c_size), ("st_edges_clamped", c_size), ("st_edges_unreadable", c_size),
    ("st_edges_why", ctypes.c_char * 512), ("meanmiss_rms", c_dbl), ("meanmiss_heldout", c_dbl),
    ("mean_teach", swfs_mean_teach_result)])
swfs_clock = _s("swfs_clock", [("epoch", ctypes.c_int64), ("offset", c_dbl), ("drift", c_dbl), ("offset_err", c_dbl),
                               ("drift_err", c_dbl), ("fit", swfs_sync_result), ("resid", c_dbl), ("exptime", c_dbl),
                               ("wfs_period", c_dbl), ("cam_period", c_dbl), ("wfs_jitter", c_dbl),
                               ("cam_jitter", c_dbl), ("nused", c_size), ("ncam", c_size), ("nsegments", c_size)])
swfs_clock_params = _s("swfs_clock_params", [("offset_min", c_dbl), ("offset_max", c_dbl), ("drift_max", c_dbl)])
swfs_clock_run_options = _s("swfs_clock_run_options", [
    ("science", c_str), ("wfs", P(c_str)), ("nwfs", c_size), ("out", c_str), ("exptime", c_dbl),
    ("lin", swfs_linear_files), ("params", swfs_clock_params), ("prov", P(c_str)), ("nprov", c_size)])
swfs_clock_run_result = _s("swfs_clock_run_result", [("clock", swfs_clock), ("wfs_dropped", c_u64),
                                                     ("cam_dropped", c_u64), ("wfs_frames", c_size),
                                                     ("wfs_files", c_size)])
SPECKLES_RUN_FIELDS = [("nout", c_size), ("ncubes", c_size), ("nok", c_size), ("ratio", c_dbl), ("lag", c_dbl),
                       ("wfs_hz", c_dbl)]
swfs_orient_check_result = _s("swfs_orient_check_result", [
    ("corr", c_dbl * 8), ("best", c_int), ("ref", c_int), ("diff", c_dbl), ("diff_se", c_dbl), ("npix", c_size),
    ("nframes", c_size)])
swfs_speckles_run_result = _s("swfs_speckles_run_result", SPECKLES_RUN_FIELDS + [
    ("info", swfs_pipeline_info), ("resmean_rms", c_dbl), ("wavelen", c_dbl), ("taught", c_int),
    ("teach_map", ctypes.c_char * 4200), ("teach_fallback", ctypes.c_char * 1024), ("st_found", c_int), ("st_train_vx", c_dbl),
    ("st_train_vy", c_dbl), ("st_obs_vx", c_dbl), ("st_obs_vy", c_dbl), ("st_mismatch", c_dbl),
    ("st_obs_nlayers", c_size), ("st_train_nlayers", c_size),
    ("st_corr_train", c_dbl * RECON_MAXLAGS), ("st_corr_spread", c_dbl * RECON_MAXLAGS),
    ("st_corr_obs", c_dbl * RECON_MAXLAGS),
    ("st_corr_excess", c_dbl), ("st_corr_worst", c_size), ("st_lags", ctypes.c_long * RECON_MAXLAGS),
    ("st_edges_joined", c_size), ("st_edges_clamped", c_size), ("st_edges_unreadable", c_size),
    ("st_edges_why", ctypes.c_char * 512), ("teach_reused", c_int), ("teach_fingerprint", ctypes.c_char * 17),
    ("curl_noise", c_dbl), ("modal_regularized", c_int), ("modal_lsq", c_dbl), ("meanmiss_heldout", c_dbl),
    ("mean_teach", swfs_mean_teach_result), ("meanmiss_rms", c_dbl), ("loops_map", swfs_loops_map_result),
    ("orient_done", c_int), ("orient", swfs_orient_check_result), ("orient_adopted", c_int),
    ("dm_choice_done", c_int), ("dm_gauss_chosen", c_int), ("dm_gauss_coupling", c_dbl), ("dm_corr", c_dbl * 2),
    ("dm_corr_diff", c_dbl), ("dm_corr_se", c_dbl), ("dm_npix", c_size), ("dm_other_map", ctypes.c_char * 4200),
    ("dm_fallback", ctypes.c_char * 1024)])
swfs_wind_run_result = _s("swfs_wind_run_result", [("est", swfs_wind_estimate), ("nframes", c_size), ("nsub", c_size),
                                                   ("pitch", c_dbl), ("rate", c_dbl)])
swfs_teach_run_options = _s("swfs_teach_run_options", [
    ("sim", swfs_ts_params), ("files", P(c_str)), ("nfiles", c_size), ("out", c_str), ("work", c_str),
    ("nloops", c_size), ("max_loops", c_size), ("seed", c_u64), ("modes_from_slopes", c_int), ("noise_from_slopes", c_int),
    ("prov", P(c_str)), ("nprov", c_size), ("progress", PROGRESS_FN), ("progress_ctx", c_ptr),
    ("fingerprint", c_str), ("coupling_from_recon", c_int)])
TEACH_CHOSEN = {0: "spacetime", 1: "perframe", 2: "perframe_mixed", 3: "perframe_prior", 4: "spacetime_prior"}
SPACETIME_WARN_WIND, SPACETIME_WARN_CORR = 1, 2  # run.h swfs_spacetime_warns
swfs_modal_slopes_options = _s("swfs_modal_slopes_options", [
    ("files", P(c_str)), ("nfiles", c_size), ("cm", c_str), ("outdir", c_str), ("imat", c_str)])
swfs_modal_slopes_result = _s("swfs_modal_slopes_result", [
    ("ncoef", c_size), ("nslopes", c_size), ("rank", c_size), ("nframes", c_size), ("cond", c_dbl), ("resid", c_dbl),
    ("lsq_ratio", c_dbl), ("lsq_warns", c_int)])
swfs_ts_coupling = _s("swfs_ts_coupling", [
    ("coupling", c_dbl), ("misfit", c_dbl), ("misfit_interp", c_dbl), ("rank", c_size), ("gaussian", c_int)])
swfs_teach_run_result = _s("swfs_teach_run_result", [
    ("wind", swfs_wind_run_result), ("nlayers", c_size), ("lags", ctypes.c_long * 5), ("nlags", c_size),
    ("nloops", c_size), ("map_inputs", c_size), ("loop_frames", c_size), ("loop_frames_described", c_size),
    ("st_misfit_rms", c_dbl), ("st_truth_rms", c_dbl), ("check", swfs_speckles_run_result),
    ("warns", c_int), ("chosen", c_int), ("ao_modes", c_size), ("knee_obs", c_size), ("ncal", c_size),
    ("cal_modes", c_size * 4), ("cal_knee", c_size * 4), ("seconds", c_dbl), ("out_points", c_size),
    ("dm_pitch", c_dbl), ("out_pitch", c_dbl), ("noise_rms", c_dbl), ("noise_cells", c_size),
    ("noise_share", c_dbl), ("slope_noise", c_dbl), ("st_loops", c_size), ("max_loops", c_size),
    ("curve_first", swfs_learn_run_result),
    ("curve", swfs_learn_run_result), ("curve_doubled", swfs_learn_run_result), ("project_rank", c_size),
    ("project_slopes", c_size),
    ("zonal_misfit", c_dbl * 6), ("zonal_best", c_size), ("misfit_modal", c_dbl), ("zonal", c_int),
    ("tcorr", c_dbl * 8), ("tcorr_lags", ctypes.c_long * 8), ("ntcorr", c_size), ("nspeed", c_size),
    ("speed_cal", c_dbl * 8), ("speed_misfit", c_dbl * 8), ("prior_speed", c_dbl), ("asked_loops", c_size),
    ("curve_asked", swfs_learn_run_result), ("coupling_done", c_int), ("coupling", swfs_ts_coupling)])
swfs_estimate_run_options = _s("swfs_estimate_run_options", [
    ("science", c_str), ("speckles", c_str), ("out", c_str), ("read_noise", c_dbl), ("gain", c_dbl),
    ("g_smooth_lod", c_dbl), ("block", c_size), ("prov", P(c_str)), ("nprov", c_size), ("progress", PROGRESS_FN),
    ("progress_ctx", c_ptr), ("team", c_ptr)])
swfs_estimate_run_result = _s("swfs_estimate_run_result", [("halo", P(swfs_halo)), ("geom", swfs_geom),
                                                           ("noise", swfs_noise), ("circ_core", c_dbl),
                                                           ("g_smooth_assumed", c_int)])

swfs_pupil_run_options = _s("swfs_pupil_run_options", [
    ("halos", P(c_str)), ("nhalo", c_size), ("out", c_str), ("mask", c_str), ("truth", c_str),
    ("pupil", swfs_pupil_options), ("prov", P(c_str)), ("nprov", c_size)])
swfs_pupil_run_result = _s("swfs_pupil_run_result", [
    ("pupil", P(swfs_pupil_result)), ("halo", P(swfs_halo)), ("geom", swfs_geom), ("chosen", c_size),
    ("explained", P(c_dbl)), ("ncommon", c_size), ("err", c_dbl), ("truth_rms", c_dbl), ("truth_rms_ptt", c_dbl),
    ("ran_away", c_int), ("err_kept", c_dbl)])
swfs_dmfit_options = _s("swfs_dmfit_options", [
    ("influence", c_int), ("coupling", c_dbl), ("pitch", c_dbl), ("modes", c_size), ("reg", c_dbl), ("rcond", c_dbl),
    ("rim", c_int)])
DMFIT_STATS_FIELDS = ["target_rms", "modal_rms", "filtered_rms", "fit_rms", "fiterr_rms", "unfit_rms", "cmd_rms",
                      "cmd_min", "cmd_max"]
swfs_dmfit_stats = _s("swfs_dmfit_stats", [(n, c_dbl) for n in DMFIT_STATS_FIELDS])
swfs_dmoffsets_run_options = _s("swfs_dmoffsets_run_options", [
    ("pupil", c_str), ("actuators", c_str), ("hexapolar", c_dbl), ("out", c_str), ("fit", swfs_dmfit_options),
    ("prov", P(c_str)), ("nprov", c_size)])
swfs_dmoffsets_run_result = _s("swfs_dmoffsets_run_result", [("nact", c_size), ("active", c_size), ("pitch", c_dbl),
                                                             ("stats", swfs_dmfit_stats)])
REPORT_MAX = dict(figures=96, ranges=64, notes=64, levels=16)  # SWFS_REPORT_MAX_* (report.h)
swfs_report_options = _s("swfs_report_options", [("pct_lo", c_dbl), ("pct_hi", c_dbl), ("log_decades", c_dbl),
                                                 ("pixel_i", c_long), ("pixel_j", c_long), ("title", c_str)])
swfs_report_range = _s("swfs_report_range", [("name", ctypes.c_char * 24), ("lo", c_dbl), ("hi", c_dbl), ("log", c_int)])
swfs_report_figure = _s("swfs_report_figure", [("file", ctypes.c_char * 64), ("width", c_int), ("height", c_int)])
REPORT_LEVEL_FIELDS = ["sigma", "valid_fraction", "median_snr", "wfe_rms", "strehl", "ncp_rms", "err_rms"]
swfs_report_level = _s("swfs_report_level", [(n, c_dbl) for n in REPORT_LEVEL_FIELDS] + [("nfigures", c_size)])
REPORT_KEY_FIELDS = ["frames", "valid_fraction", "median_snr", "wfe_rms", "wfe_pv", "strehl", "ncp_rms", "err_rms",
                     "tau0_median"]
swfs_report_summary = _s("swfs_report_summary", [
    ("nfigures", c_size), ("figures", swfs_report_figure * REPORT_MAX["figures"]), ("nranges", c_size),
    ("ranges", swfs_report_range * REPORT_MAX["ranges"]), ("nnotes", c_size),
    ("notes", (ctypes.c_char * 200) * REPORT_MAX["notes"])] + [(n, c_dbl) for n in REPORT_KEY_FIELDS] + [
    ("pixel_i", c_long), ("pixel_j", c_long), ("pixel_halo_phase", c_dbl), ("pixel_fit_phase", c_dbl),
    ("html", ctypes.c_char * 4096), ("demo", c_int), ("nlevels", c_size),
    ("levels", swfs_report_level * REPORT_MAX["levels"]), ("recovery_rows", c_size), ("loop_rows", c_size)])
swfs_loop_params = _s("swfs_loop_params", [
    ("iterations", c_size), ("gain", c_dbl), ("sigma", c_dbl), ("act_pitch", c_dbl), ("act_xy", P(c_dbl)),
    ("nact", c_size), ("act_name", c_str), ("fit", swfs_dmfit_options), ("pupil", swfs_pupil_options),
    ("annulus_in", c_dbl), ("annulus_out", c_dbl)])
LOOP_ITER_FIELDS = ["resid_rms", "resid_rms_ptt", "strehl", "strehl_ao", "strehl_marechal", "contrast", "contrast_ao",
                    "contrast_ncp", "est_rms", "est_err", "median_snr"]
swfs_loop_iter = _s("swfs_loop_iter", [(n, c_dbl) for n in LOOP_ITER_FIELDS]
                    + [("fit", swfs_dmfit_stats), ("seconds", c_dbl)])
swfs_loop_result = _s("swfs_loop_result", [
    ("params", swfs_loop_params), ("sim", swfs_sim_params), ("geom", swfs_geom), ("nrows", c_size), ("nact", c_size),
    ("pitch", c_dbl), ("rows", P(swfs_loop_iter)), ("residual", P(swfs_real)), ("estimate", P(swfs_real)),
    ("dm_surface", P(swfs_real)), ("commands", P(swfs_real)), ("actuators", P(swfs_real)), ("pupil", P(swfs_real)),
    ("seconds", c_dbl)])
swfs_shm_source_options = _s("swfs_shm_source_options", [
    ("dir", c_str), ("wfs", P(c_str)), ("nwfs", c_size), ("camera", c_str), ("nslopes", c_size), ("nfx", c_size),
    ("nfy", c_size), ("sync", swfs_framesync_options), ("poll", c_dbl), ("timeout", c_dbl), ("idle", c_dbl),
    ("stop", c_ptr), ("ring", c_size)])
swfs_shm_source_stats = _s("swfs_shm_source_stats", [
    ("sync", swfs_framesync_stats), ("ring_overruns", c_u64), ("reopens", c_u64), ("lag_count", c_size),
    ("lag_median", c_dbl), ("lag_p99", c_dbl), ("lag_max", c_dbl), ("seconds", c_dbl)])
swfs_live_options = _s("swfs_live_options", [
    ("run", swfs_stream_run_options), ("src", swfs_shm_source_options), ("dm_out", c_str), ("dm_file", c_str),
    ("dmfit", swfs_dmfit_options), ("dm_gain", c_dbl), ("dm_max_step", c_dbl), ("dm_max_rms", c_dbl),
    ("dm_scale", c_dbl), ("dm_settle", c_dbl), ("dm_keep", c_int), ("dm_final", c_int), ("dm_tiptilt", c_int)])
swfs_live_result = _s("swfs_live_result", [
    ("run", swfs_stream_run_result), ("src", swfs_shm_source_stats), ("dm_updates", c_size), ("dm_step_rms", c_dbl),
    ("dm_total_rms", c_dbl), ("dm_fixed", c_size)])
swfs_replay_options = _s("swfs_replay_options", [
    ("timing", c_str), ("science", c_str), ("slopes", c_str), ("dir", c_str), ("wfs_name", c_str),
    ("camera_name", c_str), ("wfs_rate", c_dbl), ("speed", c_dbl), ("drop_wfs", c_dbl), ("drop_camera", c_dbl),
    ("jitter", c_dbl), ("seed", c_u64), ("depth", c_size), ("wfs_type", c_int), ("camera_type", c_int),
    ("wait_reader", c_dbl), ("restart_after", c_size), ("drop_log", c_str), ("remove", c_int),
    ("progress", PROGRESS_FN), ("progress_ctx", c_ptr), ("wfs_log", c_str)])
swfs_replay_result = _s("swfs_replay_result", [
    ("wfs_frames", c_size), ("camera_frames", c_size), ("wfs_dropped", c_size), ("camera_dropped", c_size),
    ("restarts", c_size), ("wfs_rate", c_dbl), ("ratio", c_dbl), ("seconds", c_dbl), ("late_max", c_dbl)])
LIVE_LOOP_MAX = 32
swfs_live_loop_options = _s("swfs_live_loop_options", [
    ("sim", swfs_ts_params), ("dir", c_str), ("iterations", c_size), ("speed", c_dbl), ("batch", c_size),
    ("dmfit", swfs_dmfit_options), ("gain", c_dbl), ("max_step", c_dbl), ("max_rms", c_dbl), ("pupil_source", c_int),
    ("tiptilt", c_int), ("stop", c_ptr), ("prov", P(c_str)), ("nprov", c_size), ("progress", PROGRESS_FN),
    ("progress_ctx", c_ptr)])
swfs_live_loop_state = _s("swfs_live_loop_state", [
    ("residual_rms", c_dbl), ("estimate_err", c_dbl), ("dm_rms", c_dbl), ("frames_used", c_size),
    ("lag_median", c_dbl), ("lag_p99", c_dbl)])
swfs_live_loop_result = _s("swfs_live_loop_result", [
    ("nstates", c_size), ("s", swfs_live_loop_state * (LIVE_LOOP_MAX + 1)), ("seconds", c_dbl)])
swfs_demo_run_options = _s("swfs_demo_run_options", [
    ("outdir", c_str), ("sim", swfs_sim_params), ("levels", P(c_dbl)), ("nlevels", c_size),
    ("loop", swfs_loop_params), ("report", c_int), ("config", c_str), ("prov", P(c_str)), ("nprov", c_size),
    ("progress", PROGRESS_FN), ("progress_ctx", c_ptr)])
swfs_demo_run_result = _s("swfs_demo_run_result", [
    ("sim", P(swfs_sim_result)), ("nlevels", c_size), ("levels", P(swfs_recovery)), ("level_seconds", P(c_dbl)),
    ("loop", P(swfs_loop_result)), ("ncp_rms_ptt", c_dbl), ("sim_seconds", c_dbl), ("seconds", c_dbl),
    ("html", ctypes.c_char * 4096)])
STRUCTS = [v for v in list(globals().values()) if isinstance(v, type) and issubclass(v, Struct) and v._cname_]
SOURCE_FN = ctypes.CFUNCTYPE(c_int, c_ptr, P(swfs_batch))
UPDATE_FN = ctypes.CFUNCTYPE(c_int, c_ptr, c_ptr, c_int)

# ---- prototypes ----------------------------------------------------------------------

_PROTOS = {
    # status.h
    "swfs_last_error": (c_str, []),
    "swfs_clear_error": (None, []),
    "swfs_status_name": (c_str, [c_int]),
    # array.h
    "swfs_real_alloc": (P(swfs_real), [c_size, c_size, c_size]),
    "swfs_cplx_alloc": (P(swfs_cplx), [c_size, c_size, c_size]),
    "swfs_real_free": (None, [P(swfs_real)]),
    "swfs_cplx_free": (None, [P(swfs_cplx)]),
    "swfs_free": (None, [c_ptr]),
    # parallel.h
    "swfs_blas_set_threads": (None, [c_int]),
    "swfs_blas_threads": (c_int, []),
    "swfs_blas_kernel": (None, [P(swfs_blas_kernel_info)]),
    # geom.h
    "swfs_geom_init": (None, [P(swfs_geom)]),
    "swfs_geom_require": (c_int, [P(swfs_geom), c_str]),
    # config.h
    "swfs_config_new": (c_ptr, []),
    "swfs_config_free": (None, [c_ptr]),
    "swfs_config_load": (c_int, [c_ptr, c_str]),
    "swfs_config_set_kv": (c_int, [c_ptr, c_str, c_str]),
    "swfs_config_has": (c_int, [c_ptr, c_str]),
    "swfs_ts_config_gives_filter": (c_int, [c_ptr]),
    "swfs_config_check_unused": (c_int, [c_ptr]),
    # accum.h
    "swfs_accum_create": (P(swfs_accum), [c_size, c_size]),
    "swfs_accum_free": (None, [P(swfs_accum)]),
    "swfs_accum_reset": (None, [P(swfs_accum)]),
    "swfs_accum_add": (c_int, [P(swfs_accum), P(c_dbl), c_ptr]),
    "swfs_accum_merge": (c_int, [P(swfs_accum), P(swfs_accum)]),
    "swfs_accum_has_regress": (c_int, [P(swfs_accum)]),
    "swfs_accum_state_len": (c_size, [c_size, c_size]),
    "swfs_accum_export": (None, [P(swfs_accum), P(c_dbl)]),
    "swfs_accum_import": (c_int, [P(swfs_accum), P(c_dbl)]),
    "swfs_accum_merge_state": (c_int, [P(c_dbl), P(c_dbl), c_size, c_size]),
    # estimate.h
    "swfs_estimate": (c_int, [P(swfs_accum), P(swfs_noise), P(swfs_estimate_options), P(P(swfs_halo))]),
    "swfs_halo_free": (None, [P(swfs_halo)]),
    "swfs_halo_write": (c_int, [P(swfs_halo), c_str, P(swfs_geom), P(c_str), c_size]),
    "swfs_halo_read": (c_int, [c_str, P(P(swfs_halo)), P(swfs_geom)]),
    "swfs_phase_shift_map": (c_int, [P(c_dbl), P(c_dbl), c_size, c_size, P(c_dbl), c_ptr, P(c_dbl), P(c_dbl),
                                     P(c_dbl)]),
    # checkpoint.h
    "swfs_accum_save": (c_int, [P(swfs_accum), c_str, P(swfs_geom), P(c_str), c_size]),
    "swfs_accum_load": (c_int, [c_str, P(P(swfs_accum)), P(swfs_geom)]),
    "swfs_accum_merge_files": (c_int, [P(c_str), c_size, P(P(swfs_accum)), P(swfs_geom)]),
    # pupil.h
    "swfs_pupil_options_default": (None, [P(swfs_pupil_options)]),
    "swfs_halo_choose": (c_int, [P(P(swfs_halo)), P(c_str), c_size, P(c_dbl), P(c_size), P(c_size)]),
    "swfs_pupil_estimate": (c_int, [P(swfs_halo), P(swfs_geom), P(swfs_real), P(swfs_pupil_options),
                                    P(P(swfs_pupil_result))]),
    "swfs_pupil_result_free": (None, [P(swfs_pupil_result)]),
    "swfs_pupil_explained_rings": (None, [P(swfs_real), c_dbl, P(c_dbl), c_size]),
    "swfs_pupil_explained_nrings": (c_size, [P(swfs_real), c_dbl]),
    "swfs_pupil_write": (c_int, [P(swfs_pupil_result), c_str, P(swfs_geom), P(c_str), c_size]),
    "swfs_pupil_run_options_default": (None, [P(swfs_pupil_run_options)]),
    "swfs_pupil_run": (c_int, [P(swfs_pupil_run_options), P(swfs_pupil_run_result)]),
    "swfs_pupil_run_result_free": (None, [P(swfs_pupil_run_result)]),
    "swfs_demo_run_options_default": (None, [P(swfs_demo_run_options)]),
    "swfs_demo_run": (c_int, [P(swfs_demo_run_options), P(swfs_demo_run_result)]),
    "swfs_demo_run_result_free": (None, [P(swfs_demo_run_result)]),
    "swfs_wfe_compare": (c_int, [P(c_dbl), P(c_dbl), P(c_dbl), c_size, P(c_dbl), P(c_dbl), P(c_dbl)]),
    "swfs_wfe_remove_ptt": (c_dbl, [P(c_dbl), P(c_dbl), c_size]),
    # aperture.h
    "swfs_aperture_make": (c_int, [P(c_dbl), c_size, c_dbl, c_dbl, c_dbl, c_int, c_dbl]),
    "swfs_zernike": (c_dbl, [c_int, c_int, c_dbl, c_dbl]),
    # fits.h
    "swfs_fits_in_open": (c_int, [P(c_ptr), c_str, c_str]),
    "swfs_fits_in_close": (None, [c_ptr]),
    "swfs_fits_in_shape": (P(swfs_fits_shape), [c_ptr]),
    "swfs_fits_in_read_real_all": (c_int, [c_ptr, P(P(swfs_real))]),
    "swfs_fits_in_read_cplx_all": (c_int, [c_ptr, P(P(swfs_cplx))]),
    "swfs_fits_in_key_double_opt": (c_int, [c_ptr, c_str, P(c_dbl), P(c_int)]),
    "swfs_fits_in_key_string_opt": (c_int, [c_ptr, c_str, ctypes.c_char_p, c_size, P(c_int)]),
    "swfs_fits_in_geom": (c_int, [c_ptr, P(swfs_geom)]),
    "swfs_fits_out_create": (c_int, [P(c_ptr), c_str]),
    "swfs_fits_out_commit": (c_int, [c_ptr]),
    "swfs_fits_out_abort": (None, [c_ptr]),
    "swfs_fits_out_real": (c_int, [c_ptr, c_str, P(swfs_real), c_int]),
    "swfs_fits_out_cplx": (c_int, [c_ptr, c_str, P(swfs_cplx), c_int]),
    "swfs_fits_out_key_double": (c_int, [c_ptr, c_str, c_dbl, c_str]),
    "swfs_fits_out_key_long": (c_int, [c_ptr, c_str, c_long, c_str]),
    "swfs_fits_out_key_string": (c_int, [c_ptr, c_str, c_str, c_str]),
    "swfs_fits_out_set_stamp": (c_int, [c_ptr, P(swfs_geom), P(c_str), c_size]),
    # wfs.h
    "swfs_actuators_hexapolar": (c_int, [c_dbl, c_dbl, c_dbl, P(P(c_dbl)), P(c_size)]),
    "swfs_actuators_square": (c_int, [c_dbl, c_dbl, c_dbl, P(P(c_dbl)), P(c_size)]),
    "swfs_geom_read_file": (c_int, [c_str, P(swfs_geom)]),
    "swfs_shwfs_create": (c_int, [P(P(swfs_shwfs)), c_size, c_dbl, P(c_dbl), c_size, c_dbl, c_dbl]),
    "swfs_shwfs_free": (None, [P(swfs_shwfs)]),
    "swfs_shwfs_measure": (None, [P(swfs_shwfs), P(c_dbl), P(c_dbl)]),
    "swfs_interaction_matrix": (c_int, [P(swfs_shwfs), P(swfs_sparse), P(P(c_dbl))]),
    "swfs_dm_modes": (c_int, [P(swfs_sparse), P(c_dbl), c_size, P(P(c_dbl))]),
    "swfs_slopes_remove_tiptilt": (None, [P(c_dbl), c_size, P(ctypes.c_ubyte)]),
    "swfs_wind_from_slopes": (c_int, [P(c_dbl), c_size, c_size, c_size, P(ctypes.c_ubyte), c_dbl, c_dbl,
                                      P(swfs_wind_estimate)]),
    "swfs_recon_svd": (c_int, [P(c_dbl), c_size, c_size, c_dbl, c_size, P(P(swfs_recon))]),
    "swfs_recon_map": (c_int, [P(c_dbl), c_size, c_size, P(c_dbl), c_size, c_dbl, P(P(swfs_recon))]),
    "swfs_recon_vk": (c_int, [P(c_dbl), c_size, c_size, P(c_dbl), c_dbl, P(c_dbl), c_size, c_dbl,
                              P(P(swfs_recon))]),
    "swfs_vk_covariance": (c_int, [P(c_dbl), c_size, c_dbl, P(c_dbl)]),
    "swfs_slopes_noise_var": (c_int, [P(c_dbl), c_size, c_size, P(c_dbl), c_size, P(c_dbl)]),
    "swfs_slopes_white_noise": (c_int, [P(c_dbl), c_size, c_size, c_size, P(ctypes.c_ubyte), P(c_dbl), P(c_size), P(c_dbl)]),
    "swfs_linear_files_default": (None, [P(swfs_linear_files)]),
    "swfs_slopes_curl_noise": (c_int, [P(c_dbl), c_size, c_size, c_size, P(ctypes.c_ubyte), P(c_dbl), P(c_dbl)]),
    "swfs_recon_modal": (c_int, [P(c_dbl), c_size, c_size, P(c_dbl), c_size, c_size, P(P(swfs_recon))]),
    "swfs_recon_free": (None, [P(swfs_recon)]),
    "swfs_slopes_stack": (None, [P(c_dbl), c_size, c_size, P(c_long), c_size, c_size, c_size, P(c_dbl)]),
    "swfs_lags_read": (c_int, [c_str, c_size, P(c_long)]),
    "swfs_lags_check": (c_int, [P(c_long), c_size, c_str]),
    "swfs_recon_project_tiptilt": (c_int, [P(swfs_recon), P(ctypes.c_ubyte)]),
    "swfs_recon_apply": (None, [P(swfs_recon), P(c_dbl), P(c_dbl)]),
    "swfs_recon_write": (c_int, [P(swfs_recon), c_str]),
    "swfs_recon_read": (c_int, [c_str, P(P(swfs_recon))]),
    "swfs_actuators_write": (c_int, [P(c_dbl), c_size, c_str]),
    "swfs_actuators_read": (c_int, [c_str, P(P(c_dbl)), P(c_size)]),
    # interp.h
    "swfs_interp_ct_grid": (c_int, [P(c_dbl), c_size, c_size, c_dbl, P(c_dbl), P(P(swfs_sparse)), P(c_size)]),
    "swfs_sparse_free": (None, [P(swfs_sparse)]),
    # lmodel.h
    "swfs_basis_from_grid": (c_int, [P(P(swfs_sparse)), P(c_dbl), c_size, c_size, c_size, P(swfs_dm_registration),
                                     P(c_dbl), c_size, c_dbl, P(c_size)]),
    "swfs_basis_from_pupil": (c_int, [P(P(swfs_sparse)), P(c_dbl), c_size, c_size, P(c_dbl)]),
    "swfs_grid_interp": (c_int, [P(P(swfs_sparse)), c_size, c_size, P(swfs_dm_registration), P(c_dbl), c_size, c_dbl,
                                 P(c_size)]),
    # speckles.h
    "swfs_speckles_subtract_static": (c_int, [P(swfs_cplx), P(c_size), P(c_size), c_size, c_int]),
    "swfs_speckles_recon_tilt": (c_int, [P(swfs_speckle_model), P(c_dbl), P(P(c_dbl)), P(P(c_dbl))]),
    "swfs_speckles_expand_frames": (c_size, [c_ptr, c_size]),
    "swfs_speckles_expand": (c_int, [P(c_dbl), c_size, c_size, P(c_dbl), c_ptr, c_size, P(c_dbl), c_ptr]),
    "swfs_speckle_model_create": (c_int, [P(P(swfs_speckle_model)), P(c_dbl), c_size, P(c_dbl), c_size, c_dbl,
                                          c_dbl, c_size, P(swfs_recon), c_dbl, c_size, c_int]),
    "swfs_speckle_model_free": (None, [P(swfs_speckle_model)]),
    "swfs_speckle_model_set_map": (c_int, [P(swfs_speckle_model), P(c_dbl), c_size, c_dbl, c_int]),
    "swfs_speckle_model_set_vk": (c_int, [P(swfs_speckle_model), P(c_dbl), c_dbl, P(c_dbl), c_size, c_dbl,
                                          c_int]),
    # engine.h
    "swfs_engine_create": (c_ptr, [P(swfs_engine_config)]),
    "swfs_engine_free": (None, [c_ptr]),
    "swfs_engine_nthreads": (c_int, [c_ptr]),
    "swfs_engine_npin": (c_size, [c_ptr]),
    "swfs_engine_add_wfs": (c_int, [c_ptr, P(c_dbl), c_dbl]),
    "swfs_engine_end_exposure": (c_int, [c_ptr, c_ptr]),
    "swfs_engine_reset": (None, [c_ptr]),
    "swfs_engine_process": (c_int, [c_ptr, P(c_dbl), c_size, c_ptr, c_size, c_ptr]),
    "swfs_engine_process_wfs": (c_int, [c_ptr, P(c_dbl), c_size, c_ptr]),
    "swfs_engine_schedule": (c_size, [c_dbl, c_dbl, c_size, c_ptr]),
    # pipeline.h
    "swfs_pipeline_options_default": (None, [P(swfs_pipeline_options)]),
    "swfs_pipeline_create": (c_int, [P(c_ptr), P(swfs_geom), c_size, c_size, P(c_dbl), c_size, P(c_dbl), c_size,
                                     P(swfs_recon), P(c_dbl), c_size, P(swfs_pipeline_options)]),
    "swfs_pipeline_free": (None, [c_ptr]),
    "swfs_pipeline_process": (c_int, [c_ptr, P(c_dbl), c_size, c_ptr, c_size, c_ptr]),
    "swfs_pipeline_process_wfs": (c_int, [c_ptr, P(c_dbl), c_size, c_ptr]),
    "swfs_pipeline_flat_halo": (c_int, [c_ptr, c_ptr]),
    "swfs_pipeline_mean_wavefront": (c_int, [c_ptr, P(c_dbl), P(c_size), P(c_dbl)]),
    "swfs_pipeline_mean_reset": (None, [c_ptr]),
    "swfs_pipeline_set_mean_offset": (c_int, [c_ptr, P(c_dbl)]),
    "swfs_pipeline_mean_loops": (c_int, [c_ptr, P(c_str), c_size, P(c_dbl), P(c_dbl)]),
    "swfs_pipeline_get_info": (None, [c_ptr, P(swfs_pipeline_info)]),
    "swfs_pipeline_recon": (P(swfs_recon), [c_ptr]),
    "swfs_pipeline_create_linear": (c_int, [P(c_ptr), P(swfs_geom), c_size, c_size, P(c_dbl), P(swfs_linear_input),
                                            P(c_dbl), c_size, c_ptr]),
    "swfs_pipeline_tilt_rows": (P(c_dbl), [c_ptr]),
    "swfs_pipeline_model": (P(swfs_speckle_model), [c_ptr]),
    # stream.h
    "swfs_stream_options_default": (None, [P(swfs_stream_options)]),
    "swfs_stream_create": (c_int, [P(c_ptr), c_ptr, P(swfs_stream_options)]),
    "swfs_stream_free": (None, [c_ptr]),
    "swfs_framesync_options_default": (None, [P(swfs_framesync_options)]),
    "swfs_framesync_create": (c_int, [P(c_ptr), c_size, P(c_size), c_size, P(swfs_framesync_options)]),
    "swfs_framesync_free": (None, [c_ptr]),
    "swfs_framesync_add_wfs": (c_int, [c_ptr, c_size, c_u64, ctypes.c_int64, P(c_dbl), c_dbl]),
    "swfs_framesync_add_camera": (c_int, [c_ptr, c_u64, ctypes.c_int64, P(c_dbl), c_dbl]),
    "swfs_framesync_expect": (None, [c_ptr, c_int, c_size, c_u64, c_int]),
    "swfs_framesync_settle": (None, [c_ptr, ctypes.c_int64]),
    "swfs_framesync_next": (c_int, [c_ptr, c_dbl, c_int, P(swfs_batch)]),
    "swfs_framesync_batch_stamps": (P(ctypes.c_int64), [c_ptr]),
    "swfs_framesync_get_stats": (None, [c_ptr, P(swfs_framesync_stats)]),
    "swfs_framesync_nslopes": (c_size, [c_ptr]),
    "swfs_stream_push": (c_int, [c_ptr, P(swfs_batch)]),
    "swfs_stream_run": (c_int, [c_ptr, SOURCE_FN, c_ptr, UPDATE_FN, c_ptr]),
    "swfs_stream_estimate": (c_int, [c_ptr, P(P(swfs_halo))]),
    "swfs_stream_accum": (P(swfs_accum), [c_ptr]),
    "swfs_stream_static": (c_ptr, [c_ptr]),
    "swfs_stream_camera_frames": (c_size, [c_ptr]),
    "swfs_stream_wfs_frames": (c_dbl, [c_ptr]),
    "swfs_stream_seconds": (c_dbl, [c_ptr]),
    "swfs_stream_static_scale": (c_dbl, [c_ptr]),
    # mft.h
    "swfs_mft_create": (c_ptr, [c_size, c_size, c_size, c_dbl, c_int]),
    "swfs_mft_free": (None, [c_ptr]),
    "swfs_mft_forward": (c_int, [c_ptr, c_ptr, c_ptr]),
    "swfs_mft_inverse": (c_int, [c_ptr, c_ptr, c_ptr]),
    # coherence.h
    "swfs_coh_default_lags": (None, [P(c_long)]),
    "swfs_coh_options_default": (None, [P(swfs_coh_options)]),
    "swfs_coherence_compute": (c_int, [P(swfs_cplx), c_dbl, P(swfs_coh_options), P(P(swfs_coherence))]),
    "swfs_coherence_free": (None, [P(swfs_coherence)]),
    "swfs_coherence_snr_map": (c_int, [P(swfs_coherence), c_dbl, P(swfs_real)]),
    "swfs_coh_snr_factor": (c_dbl, [c_ptr, c_size, c_dbl, c_dbl]),
    "swfs_coherence_fit_wind": (c_int, [P(swfs_coherence), P(swfs_geom), P(c_dbl)]),
    "swfs_coherence_write": (c_int, [P(swfs_coherence), c_str, P(swfs_geom), P(c_str), c_size]),
    "swfs_coherence_read_input": (c_int, [c_str, P(P(swfs_cplx)), P(c_dbl), P(swfs_geom), P(c_dbl)]),
    "swfs_exposure_limit_wind": (c_dbl, [c_dbl, c_dbl, c_dbl]),
    "swfs_bandwidth_radius": (c_dbl, [c_dbl]),
    # sim.h, recovery.h, timeseries.h
    "swfs_sim_params_default": (None, [P(swfs_sim_params)]),
    "swfs_sim_params_from_config": (c_int, [c_ptr, P(swfs_sim_params)]),
    "swfs_sim_params_check": (c_int, [P(swfs_sim_params)]),
    "swfs_sim_params_format": (c_size, [P(swfs_sim_params), ctypes.c_char_p, c_size]),
    "swfs_sim_paper_run": (c_int, [P(swfs_sim_params), PROGRESS_FN, c_ptr, P(P(swfs_sim_result))]),
    "swfs_sim_paper_run_ncp": (c_int, [P(swfs_sim_params), P(c_dbl), PROGRESS_FN, c_ptr,
                                       P(P(swfs_sim_result))]),
    "swfs_sim_result_free": (None, [P(swfs_sim_result)]),
    "swfs_sim_ncp_map": (c_int, [P(swfs_sim_params), P(c_dbl), P(c_dbl), P(c_dbl), P(c_dbl)]),
    "swfs_sim_camera": (c_int, [P(swfs_real), c_dbl, c_dbl, c_u64, P(swfs_real)]),
    "swfs_sim_write": (c_int, [P(swfs_sim_result), P(swfs_real), c_dbl, c_dbl, c_str, P(c_str), c_size]),
    "swfs_recovery_run": (c_int, [P(swfs_sim_result), c_dbl, c_u64, c_str, P(c_str), c_size, P(swfs_recovery)]),
    "swfs_ts_params_default": (None, [P(swfs_ts_params)]),
    "swfs_ts_params_from_config": (c_int, [c_ptr, P(swfs_ts_params)]),
    "swfs_ts_params_check": (c_int, [P(swfs_ts_params)]),
    "swfs_ts_run": (c_int, [P(swfs_ts_params), c_str, P(c_str), c_size, PROGRESS_FN, c_ptr, P(swfs_ts_summary)]),
    "swfs_ts_mode_variance": (c_int, [P(swfs_ts_params), P(c_dbl), c_size, c_size, P(P(c_dbl)), P(c_size)]),
    "swfs_mode_knee": (c_size, [P(c_dbl), c_size]),
    "swfs_ts_mode_timecorr": (c_int, [P(swfs_ts_params), P(c_dbl), c_size, c_size, P(ctypes.c_long), c_size,
                                      P(c_dbl)]),
    # run.h: reduce, sync, speckles, estimate on files
    "swfs_reduce_run_options_default": (None, [P(swfs_reduce_run_options)]),
    "swfs_reduce_run": (c_int, [P(swfs_reduce_run_options), P(swfs_reduce_run_result)]),
    "swfs_sync_run_options_default": (None, [P(swfs_sync_run_options)]),
    "swfs_sync_run": (c_int, [P(swfs_sync_run_options), P(swfs_sync_run_result)]),
    "swfs_learn_run_options_default": (None, [P(swfs_learn_run_options)]),
    "swfs_learn_run": (c_int, [P(swfs_learn_run_options), P(swfs_learn_run_result)]),
    "swfs_teach_run_options_default": (None, [P(swfs_teach_run_options)]),
    "swfs_teach_run": (c_int, [P(swfs_teach_run_options), P(swfs_teach_run_result)]),
    "swfs_modal_slopes_run": (c_int, [P(swfs_modal_slopes_options), P(swfs_modal_slopes_result)]),
    "swfs_teach_describe": (c_int, [c_ptr, c_str, c_str, c_str, c_str, c_str]),
    "swfs_teach_work_default": (c_int, [c_str, ctypes.c_char_p, c_size]),
    "swfs_spacetime_warns": (c_int, [P(swfs_speckles_run_result)]),
    "swfs_speckles_resmean_warns": (c_int, [P(swfs_speckles_run_result)]),
    "swfs_speckles_orient_warns": (c_int, [P(swfs_speckles_run_result)]),
    "swfs_speckles_orient_warning": (None, [P(swfs_speckles_run_result), ctypes.c_char_p, c_size]),
    "swfs_orient_pairing": (None, [c_int, P(swfs_sync_result)]),
    "swfs_orient_check_describe": (None, [P(swfs_orient_check_result), ctypes.c_char_p, c_size]),
    "swfs_sync_boundary_check": (c_int, [P(c_dbl), c_size, P(c_dbl), c_size, c_size, P(swfs_sync_boundary)]),
    "swfs_sync_boundary_gap": (c_int, [P(c_dbl), c_size, P(c_dbl), c_size, c_size, c_long, P(swfs_sync_gap)]),
    "swfs_speckles_run_options_default": (None, [P(swfs_speckles_run_options)]),
    "swfs_speckles_run": (c_int, [P(swfs_speckles_run_options), P(swfs_speckles_run_result)]),
    "swfs_linear_pipeline": (c_int, [P(c_ptr), P(swfs_linear_files), P(swfs_geom), c_size, c_size, P(c_dbl), c_size,
                                     P(c_dbl), c_size, P(swfs_pipeline_options)]),
    "swfs_linear_control_lags": (c_int, [P(swfs_linear_files), P(c_long), P(c_size)]),
    "swfs_map_meanmiss_attach": (c_int, [c_ptr, c_str, P(swfs_linear_files), P(swfs_geom), P(c_dbl)]),
    "swfs_meanmiss_metric": (c_int, [c_str, c_size, P(c_dbl), c_str, P(P(c_dbl)), P(c_size)]),
    "swfs_sh_pipeline": (c_int, [P(c_ptr), c_str, c_str, c_str, P(swfs_geom), c_size, c_size, P(c_dbl), c_size, P(c_dbl),
                                 c_size, P(swfs_recon), P(c_dbl), c_size, P(swfs_pipeline_options)]),
    "swfs_report_options_default": (None, [P(swfs_report_options)]),
    "swfs_report_run": (c_int, [c_str, c_str, P(swfs_report_options), P(swfs_report_summary)]),
    "swfs_dmfit_options_default": (None, [P(swfs_dmfit_options)]),
    "swfs_dmfit_create": (c_int, [P(c_ptr), P(c_dbl), c_size, P(swfs_geom), P(c_dbl), P(swfs_dmfit_options)]),
    "swfs_dmfit_free": (None, [c_ptr]),
    "swfs_dmfit_apply": (c_int, [c_ptr, P(c_dbl), P(c_dbl), P(c_dbl), P(swfs_dmfit_stats)]),
    "swfs_dmfit_surface": (None, [c_ptr, P(c_dbl), P(c_dbl)]),
    "swfs_dmfit_nact": (c_size, [c_ptr]),
    "swfs_dmfit_npup": (c_size, [c_ptr]),
    "swfs_dmfit_active": (c_size, [c_ptr]),
    "swfs_dmfit_pitch": (c_dbl, [c_ptr]),
    "swfs_dmoffsets_run_options_default": (None, [P(swfs_dmoffsets_run_options)]),
    "swfs_dmoffsets_run": (c_int, [P(swfs_dmoffsets_run_options), P(swfs_dmoffsets_run_result)]),
    "swfs_stream_run_options_default": (None, [P(swfs_stream_run_options)]),
    "swfs_stream_run_files": (c_int, [P(swfs_stream_run_options), P(swfs_stream_run_result)]),
    "swfs_live_options_default": (None, [P(swfs_live_options)]),
    "swfs_live_run": (c_int, [P(swfs_live_options), P(swfs_live_result)]),
    "swfs_replay_options_default": (None, [P(swfs_replay_options)]),
    "swfs_replay_run": (c_int, [P(swfs_replay_options), P(swfs_replay_result)]),
    "swfs_live_loop_options_default": (None, [P(swfs_live_loop_options)]),
    "swfs_live_loop_run": (c_int, [P(swfs_live_loop_options), P(swfs_live_loop_result)]),
    "swfs_clock_run_options_default": (None, [P(swfs_clock_run_options)]),
    "swfs_clock_run": (c_int, [P(swfs_clock_run_options), P(swfs_clock_run_result)]),
    "swfs_estimate_run_options_default": (None, [P(swfs_estimate_run_options)]),
    "swfs_estimate_run": (c_int, [P(swfs_estimate_run_options), P(swfs_estimate_run_result)]),
}

for _name, (_res, _args) in _PROTOS.items():
    _f = getattr(lib, _name)
    _f.restype = _res
    _f.argtypes = _args


# ---- ownership of C-allocated data ---------------------------------------------------

class Owner:
    """Frees a library object when the last Python reference to it (the wrapper object
    or any numpy view into its arrays) goes away."""
    __slots__ = ("ptr", "free", "keep", "__weakref__")

    def __init__(self, ptr, free):
        self.ptr = ptr
        self.free = free
        self.keep = []  # owners of objects the library replaced in this one, kept for their views

    def __del__(self):
        if self.ptr is not None and self.free is not None:
            self.free(self.ptr)
            self.ptr = None


def view(addr, shape, dtype, owner):
    """A numpy array over library memory at addr (no copy) that keeps `owner` alive."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape)) * dtype.itemsize
    if not addr or n == 0:
        return np.zeros(shape, dtype)
    buf = (ctypes.c_char * n).from_address(addr)
    buf._owner = owner
    return np.frombuffer(buf, dtype=dtype).reshape(shape)


def real_view(p, owner, squeeze=True):
    """numpy view of a swfs_real* (None for NULL): shape (nz, ny, nx), or (ny, nx) if nz == 1."""
    if not p:
        return None
    a = p.contents
    shape = (a.ny, a.nx) if (squeeze and a.nz == 1) else (a.nz, a.ny, a.nx)
    return view(ctypes.cast(a.data, c_ptr).value, shape, np.float64, owner)


def cplx_view(p, owner, squeeze=True):
    if not p:
        return None
    a = p.contents
    shape = (a.ny, a.nx) if (squeeze and a.nz == 1) else (a.nz, a.ny, a.nx)
    return view(a.data, shape, np.complex128, owner)


def take_real(p, squeeze=True):
    """Own a library-allocated swfs_real*: a numpy view freed with it."""
    return real_view(p, Owner(p, lib.swfs_real_free), squeeze)


def take_cplx(p, squeeze=True):
    return cplx_view(p, Owner(p, lib.swfs_cplx_free), squeeze)


def take_buffer(addr, shape, dtype):
    """A numpy view of a swfs_malloc'ed / malloc'ed buffer the caller must free with free()."""
    return view(addr, shape, dtype, Owner(addr, _libc_free))


_libc = ctypes.CDLL(None)
_libc.free.argtypes = [c_ptr]
_libc.free.restype = None


def _libc_free(p):
    _libc.free(p)


# ---- numpy inputs ----------------------------------------------------------------------

def _shape_str(shape):
    return "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"


def as_array(a, name, dtype, shape=None, ndim=None, writable=False):
    """a as a C-contiguous array of dtype, without a copy when it already is one.
    shape: expected shape with None for 'any'; ndim: allowed numbers of dimensions.
    Raises ValueError naming the argument with the expected and actual shapes."""
    dtype = np.dtype(dtype)
    arr = np.asarray(a)
    if dtype.kind == "f" and arr.dtype.kind == "c":
        raise ValueError(f"{name}: expected real values ({dtype}), got {arr.dtype}")
    if dtype.kind in "fc" and arr.dtype.kind not in "biufc":
        raise ValueError(f"{name}: expected a numeric array ({dtype}), got {arr.dtype}")
    if writable:
        if arr.dtype != dtype or not arr.flags.c_contiguous or not arr.flags.writeable:
            raise ValueError(f"{name}: expected a writable C-contiguous {dtype} array (modified in place), "
                             f"got {arr.dtype}{'' if arr.flags.c_contiguous else ' non-contiguous'}")
    else:
        arr = np.ascontiguousarray(arr, dtype=dtype)
    if ndim is not None and arr.ndim not in (ndim if isinstance(ndim, tuple) else (ndim,)):
        raise ValueError(f"{name}: expected {' or '.join(str(d) for d in (ndim if isinstance(ndim, tuple) else (ndim,)))}"
                         f" dimensions, got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(e is not None and e != g for e, g in zip(shape, arr.shape)):
            raise ValueError(f"{name}: expected shape {_shape_str(shape)}, got {arr.shape}")
    return arr


def dptr(arr):
    return arr.ctypes.data_as(P(c_dbl)) if arr is not None else None


def vptr(arr):
    return arr.ctypes.data if arr is not None else None


def real_struct(arr):
    """swfs_real over a float64 C-contiguous 2-D or 3-D array (no copy; keep arr alive)."""
    nz, ny, nx = (1,) + arr.shape if arr.ndim == 2 else arr.shape
    return swfs_real(nx, ny, nz, arr.ctypes.data_as(P(c_dbl)))


def cplx_struct(arr):
    nz, ny, nx = (1,) + arr.shape if arr.ndim == 2 else arr.shape
    return swfs_cplx(nx, ny, nz, arr.ctypes.data)


def path_list(x):
    """One path (str, bytes, os.PathLike) or an iterable of them, as a list (None: [])."""
    return [x] if isinstance(x, (str, bytes)) or hasattr(x, "__fspath__") else list(x or ())


def strings(lines):
    """(char **, n, keepalive) for provenance lines."""
    enc = [s.encode() for s in (lines or [])]
    arr = (c_str * max(1, len(enc)))(*enc)
    return arr, len(enc)


def enc(path):
    b = os.fsencode(path)
    if b"\0" in b:  # the C side would read the name up to it, another file
        raise ValueError(f"path {path!r} holds a NUL character")
    return b


def choice(table, v, name):
    """table[v] for an option spelled as one of table's keys, else ValueError naming the option
    and the spellings it takes (not a KeyError or TypeError from inside the package)."""
    try:
        return table[v]
    except (KeyError, TypeError):
        keys = ", ".join(repr(k) for k in table)
        raise ValueError(f"{name}: expected one of {keys}, got {v!r}") from None


def count(v, name, lo=0, hi=1 << 40):
    """v as a whole number in [lo, hi] for a size_t / long argument (a negative number would wrap
    to 2^64 - n, a fraction would be truncated), else ValueError naming it."""
    try:
        f = float(v)
        i = int(v)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name}: expected a whole number, got {v!r}") from None
    if f != i or not lo <= i <= hi:
        raise ValueError(f"{name}: expected a whole number from {lo} to {hi}, got {v!r}")
    return i

