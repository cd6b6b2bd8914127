/* The report: a synthetic run folder (written here with the FITS layer) gives figures of
 * the expected pixel size that are not blank, colour ranges equal to robust percentiles
 * of the data, key numbers that recover what was injected (the WFE error map, the halo
 * phase of a first-ring pixel), and an index.html in which headless Chromium loads every
 * image (skipped when chromium is not installed). */
#include "testutil.h"

#include "specklewfs/array.h"
#include "specklewfs/fits.h"
#include "specklewfs/plot.h"
#include "specklewfs/report.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#ifdef SWFS_HAVE_LIBPNG
#include <png.h>
#endif

/* ---- the synthetic run ------------------------------------------------ */

enum { NX = 40, NY = 40, NPUP = 24, NFR = 240, NLAG = 12 };
#define LAMBDA 3.8e-6
#define DIAM 6.5
#define PIXSCALE 0.25
#define RDNOISE 5.0

typedef struct run {
    double pupil[NPUP * NPUP], ncp[NPUP * NPUP], err[NPUP * NPUP];
    double complex halo[NX * NY];
    double sig2[NX * NY]; /* speckle power */
    double mean_i[NX * NY], var_i[NX * NY], valid[NX * NY];
    double err_rms, err_rms_piston, ncp_rms;
} run;

/* rms over the pupil of v minus its least-squares a + b p + c q (Cramer's rule on the 3x3
 * normal equations): independent of the library's fit. */
static double rms_without_ptt(const double *v, const double *pupil)
{
    double A[3][3] = {{0}}, b[3] = {0};
    for (int q = 0; q < NPUP; q++)
        for (int p = 0; p < NPUP; p++) {
            if (pupil[q * NPUP + p] == 0.0) continue;
            double f[3] = {1.0, p, q};
            for (int i = 0; i < 3; i++) {
                b[i] += f[i] * v[q * NPUP + p];
                for (int j = 0; j < 3; j++) A[i][j] += f[i] * f[j];
            }
        }
#define DET3(M) (M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1]) - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0]) + \
                 M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0]))
    double d = DET3(A), coef[3];
    for (int c = 0; c < 3; c++) {
        double Ac[3][3];
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) Ac[i][j] = j == c ? b[i] : A[i][j];
        coef[c] = DET3(Ac) / d;
    }
#undef DET3
    double s2 = 0;
    int cnt = 0;
    for (int q = 0; q < NPUP; q++)
        for (int p = 0; p < NPUP; p++)
            if (pupil[q * NPUP + p] != 0.0) {
                s2 += pow(v[q * NPUP + p] - coef[0] - coef[1] * p - coef[2] * q, 2);
                cnt++;
            }
    return sqrt(s2 / cnt);
}

static double theta(int i, int n) { return (double)(i - n / 2) * PIXSCALE; }
static double pupx(int p) { return ((double)p - 0.5 * (NPUP - 1)) * DIAM / NPUP; }

static void geom(swfs_geom *g)
{
    swfs_geom_init(g);
    g->wavelen = LAMBDA;
    g->teldiam = DIAM;
    g->obscur = 0.1;
    g->pixscale = PIXSCALE;
    g->pupdx = DIAM / NPUP;
    g->pupn = NPUP;
}

static void write_map(swfs_fits_out *o, const char *ext, const double *v, size_t nx, size_t ny)
{
    swfs_real *a = swfs_real_alloc(nx, ny, 1);
    assert_non_null(a);
    memcpy(a->data, v, nx * ny * sizeof *v);
    assert_ok(swfs_fits_out_real(o, ext, a, -64));
    swfs_real_free(a);
}

/* Writes the products named in `which` ("science speckles truth pupil halo wavefront
 * coherence") into dir and fills r. */
static void make_run(const char *dir, const char *which, run *r)
{
    mkdir(dir, 0777);
    char path[1024];
    swfs_geom g;
    geom(&g);
    swfs_rng rng;
    swfs_rng_seed(&rng, 7);

    /* Pupil and NCP (trefoil + a Gaussian dent, as fig:Sim-NCP), [m]. */
    double s1 = 0, s2 = 0;
    int cnt = 0;
    for (int q = 0; q < NPUP; q++)
        for (int p = 0; p < NPUP; p++) {
            double x = pupx(p), y = pupx(q), rr = hypot(x, y) / (0.5 * DIAM);
            int k = q * NPUP + p;
            r->pupil[k] = rr <= 1.0 && rr >= 0.1;
            r->ncp[k] = r->pupil[k] != 0.0 ? 60e-9 * pow(rr, 3) * cos(3 * atan2(y, x)) -
                                          80e-9 * exp(-(pow(x - 1.0, 2) + pow(y + 0.8, 2)) / (2 * 0.5 * 0.5))
                                    : 0.0;
            /* A pattern plus a tilt: the recovery error removes piston and tip/tilt (the demo's). */
            r->err[k] = r->pupil[k] != 0.0 ? 10e-9 * cos(2 * M_PI * x / 2.0) + 4e-9 * y : 0.0;
            if (r->pupil[k] != 0.0) {
                s1 += r->err[k];
                cnt++;
            }
        }
    double mean_err = s1 / cnt, m_ncp = 0;
    for (int k = 0; k < NPUP * NPUP; k++)
        if (r->pupil[k] != 0.0) {
            s2 += pow(r->err[k] - mean_err, 2);
            m_ncp += r->ncp[k] / cnt;
        }
    r->err_rms_piston = sqrt(s2 / cnt);
    r->err_rms = rms_without_ptt(r->err, r->pupil);
    double t2 = 0;
    for (int k = 0; k < NPUP * NPUP; k++)
        if (r->pupil[k] != 0.0) t2 += pow(r->ncp[k] - m_ncp, 2);
    r->ncp_rms = sqrt(t2 / cnt);

    /* Static halo: the MFT of the aberrated pupil (DESIGN.md sign), peak |Psi|^2 = 1e5. */
    for (int j = 0; j < NY; j++)
        for (int i = 0; i < NX; i++) {
            double complex s = 0;
            for (int q = 0; q < NPUP; q++)
                for (int p = 0; p < NPUP; p++) {
                    int k = q * NPUP + p;
                    if (r->pupil[k] == 0.0) continue;
                    double ph = 2 * M_PI * r->ncp[k] / LAMBDA -
                                2 * M_PI * (theta(i, NX) * pupx(p) + theta(j, NY) * pupx(q)) / DIAM;
                    s += cexp(I * ph);
                }
            int k = j * NX + i;
            r->halo[k] = s / cnt * sqrt(1e5);
            double rad = hypot(theta(i, NX), theta(j, NY));
            r->sig2[k] = 2e3 * pow(1.0 + rad * rad, -11.0 / 6.0);
            double h2 = creal(r->halo[k] * conj(r->halo[k]));
            r->mean_i[k] = h2 + r->sig2[k];
            r->var_i[k] = 2 * h2 * r->sig2[k] + r->sig2[k] * r->sig2[k];
            r->valid[k] = rad < 4.5 && !(i == 25 && j == 22);
        }

    if (strstr(which, "science")) {
        /* Frames: I = |Psi + psi|^2 + read noise, psi circular Gaussian of power sig2. */
        swfs_fits_out *os, *ok;
        snprintf(path, sizeof path, "%s/science.fits", dir);
        assert_ok(swfs_fits_out_create(&os, path));
        assert_ok(swfs_fits_out_begin(os, NULL, NX, NY, NFR, 0, -64));
        assert_ok(swfs_fits_out_geom(os, &g));
        assert_ok(swfs_fits_out_key_double(os, "RDNOISE", RDNOISE, NULL));
        snprintf(path, sizeof path, "%s/speckles.fits", dir);
        assert_ok(swfs_fits_out_create(&ok, path));
        assert_ok(swfs_fits_out_begin(ok, NULL, NX, NY, NFR, 1, -64));
        assert_ok(swfs_fits_out_geom(ok, &g));
        double *fi = malloc(NX * NY * sizeof *fi);
        double complex *fp = malloc(NX * NY * sizeof *fp);
        for (size_t t = 0; t < NFR; t++) {
            for (int k = 0; k < NX * NY; k++) {
                fp[k] = sqrt(r->sig2[k]) * swfs_rng_cnormal_value(&rng);
                double complex e = r->halo[k] + fp[k];
                fi[k] = creal(e * conj(e)) + RDNOISE * swfs_rng_normal(&rng);
            }
            assert_ok(swfs_fits_out_real_frames(os, t, 1, fi));
            assert_ok(swfs_fits_out_cplx_frames(ok, t, 1, fp));
        }
        free(fi);
        free(fp);
        assert_ok(swfs_fits_out_commit(os));
        assert_ok(swfs_fits_out_commit(ok));
    }
    if (strstr(which, "truth")) {
        swfs_fits_out *o;
        snprintf(path, sizeof path, "%s/truth.fits", dir);
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_geom(o, &g));
        write_map(o, "NCP", r->ncp, NPUP, NPUP);
        swfs_cplx *h = swfs_cplx_alloc(NX, NY, 1);
        memcpy(h->data, r->halo, sizeof r->halo);
        assert_ok(swfs_fits_out_cplx(o, "HALO", h, -64));
        swfs_cplx_free(h);
        assert_ok(swfs_fits_out_commit(o));
    }
    if (strstr(which, "pupil")) {
        swfs_fits_out *o;
        snprintf(path, sizeof path, "%s/pupil.fits", dir);
        assert_ok(swfs_fits_out_create(&o, path));
        write_map(o, NULL, r->pupil, NPUP, NPUP);
        assert_ok(swfs_fits_out_commit(o));
    }
    if (strstr(which, "halo")) {
        swfs_fits_out *o;
        snprintf(path, sizeof path, "%s/halo.fits", dir);
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_key_long(o, "NFRAMES", NFR, NULL));
        assert_ok(swfs_fits_out_geom(o, &g));
        assert_ok(swfs_fits_out_key_double(o, "VALIDFR", 0.61, NULL));
        assert_ok(swfs_fits_out_key_double(o, "MEDSNR", 7.25, NULL));
        swfs_cplx *h = swfs_cplx_alloc(NX, NY, 1);
        memcpy(h->data, r->halo, sizeof r->halo);
        assert_ok(swfs_fits_out_cplx(o, "HALO", h, -64));
        assert_ok(swfs_fits_out_cplx(o, "HALO_LF", h, -64)); /* required by the HALO.fits reader */
        swfs_cplx_free(h);
        double gain[NX * NY], vis[NX * NY], snr[NX * NY], nfr[NX * NY];
        for (int k = 0; k < NX * NY; k++) {
            double a = cabs(r->halo[k]);
            gain[k] = 1.0 + 0.05 * sin(0.3 * k);
            vis[k] = 2 * a * sqrt(r->sig2[k]) / (a * a + r->sig2[k]);
            snr[k] = sqrt((double)NFR) * a * sqrt(r->sig2[k]) / (r->mean_i[k] + RDNOISE);
            nfr[k] = NFR;
        }
        write_map(o, "GAIN", gain, NX, NY);
        write_map(o, "VISIB", vis, NX, NY);
        write_map(o, "SNR", snr, NX, NY);
        write_map(o, "MEAN_I", r->mean_i, NX, NY);
        write_map(o, "VAR_I", r->var_i, NX, NY);
        write_map(o, "MEAN_SP", r->sig2, NX, NY);
        write_map(o, "VALID", r->valid, NX, NY);
        write_map(o, "NFRAMES", nfr, NX, NY);
        assert_ok(swfs_fits_out_commit(o));
    }
    if (strstr(which, "wavefront")) {
        swfs_fits_out *o;
        snprintf(path, sizeof path, "%s/wavefront.fits", dir);
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_geom(o, &g));
        double wfe[NPUP * NPUP], amp[NPUP * NPUP];
        for (int k = 0; k < NPUP * NPUP; k++) {
            wfe[k] = r->pupil[k] != 0.0 ? r->ncp[k] + r->err[k] + 3e-9 : 0.0; /* + a piston */
            amp[k] = r->pupil[k] * (1.0 + 0.1 * swfs_rng_uniform(&rng));
        }
        write_map(o, "WFE", wfe, NPUP, NPUP);
        write_map(o, "AMPLITUDE", amp, NPUP, NPUP);
        write_map(o, "PUPIL", r->pupil, NPUP, NPUP);
        if (strstr(which, "resmean")) { /* the AO residual's time mean pupil took out */
            double rm[NPUP * NPUP];
            for (int k = 0; k < NPUP * NPUP; k++) rm[k] = r->pupil[k] != 0.0 ? 5e-9 * sin(0.2 * k) : 0.0;
            write_map(o, "RESMEAN", rm, NPUP, NPUP);
            assert_ok(swfs_fits_out_key_double(o, "RESMRMS", 3.5e-9, "[m]"));
        }
        assert_ok(swfs_fits_out_commit(o));
    }
    if (strstr(which, "coherence")) {
        swfs_fits_out *o;
        snprintf(path, sizeof path, "%s/coherence.fits", dir);
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_geom(o, &g));
        double tau0[NX * NY], trot[NX * NY], sf[NX * NY], lags[NLAG];
        swfs_cplx *mcf = swfs_cplx_alloc(NX, NY, NLAG);
        for (int l = 0; l < NLAG; l++) lags[l] = 0.005 * l;
        for (int j = 0; j < NY; j++)
            for (int i = 0; i < NX; i++) {
                int k = j * NX + i;
                tau0[k] = 0.035 + 0.02 * exp(-pow(theta(j, NY) - 0.5 * theta(i, NX), 2));
                trot[k] = i == NX / 2 ? INFINITY : 0.15 / (0.2 + fabs(theta(i, NX)));
                sf[k] = 0.5 + 0.4 * tau0[k] / 0.055;
                for (int l = 0; l < NLAG; l++)
                    mcf->data[(size_t)l * NX * NY + (size_t)k] =
                        exp(-0.5 * pow(lags[l] / tau0[k], 2)) *
                        cexp(I * (isfinite(trot[k]) ? 0.5 * M_PI * lags[l] / trot[k] : 0.0));
            }
        write_map(o, "MEAN_SP", r->sig2, NX, NY);
        write_map(o, "TAU0", tau0, NX, NY);
        write_map(o, "TROT", trot, NX, NY);
        write_map(o, "SNR_FACT", sf, NX, NY);
        assert_ok(swfs_fits_out_cplx(o, "MCF", mcf, -64));
        write_map(o, "LAGS", lags, NLAG, 1);
        swfs_cplx_free(mcf);
        assert_ok(swfs_fits_out_commit(o));
    }
}

/* ---- checks ----------------------------------------------------------- */

static int cmpd(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Independent percentile: sort the finite values, interpolate linearly. */
static double pct(const double *v, size_t n, const double *mask, double p)
{
    double *w = malloc(n * sizeof *w);
    size_t m = 0;
    for (size_t k = 0; k < n; k++)
        if (isfinite(v[k]) && (!mask || mask[k] > 0.5)) w[m++] = v[k];
    qsort(w, m, sizeof *w, cmpd);
    double pos = p / 100.0 * (double)(m - 1);
    size_t k = (size_t)pos;
    double r = k + 1 < m ? w[k] + (pos - (double)k) * (w[k + 1] - w[k]) : w[k];
    free(w);
    return r;
}

/* Width and height from the PNG signature + IHDR chunk (24 bytes). */
static void png_size(const char *path, int *w, int *h)
{
    unsigned char b[24];
    FILE *f = fopen(path, "rb");
    assert_non_null(f);
    assert_int_equal(fread(b, 1, 24, f), 24);
    fclose(f);
    static const unsigned char sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
    assert_memory_equal(b, sig, 8);
    assert_memory_equal(b + 12, "IHDR", 4);
    *w = (int)((unsigned)b[16] << 24 | (unsigned)b[17] << 16 | (unsigned)b[18] << 8 | b[19]);
    *h = (int)((unsigned)b[20] << 24 | (unsigned)b[21] << 16 | (unsigned)b[22] << 8 | b[23]);
}

/* Not blank: decoded grey levels vary and a good part of the page is not background. */
static void check_not_blank(const char *path)
{
#ifdef SWFS_HAVE_LIBPNG
    png_image im;
    memset(&im, 0, sizeof im);
    im.version = PNG_IMAGE_VERSION;
    assert_true(png_image_begin_read_from_file(&im, path));
    im.format = PNG_FORMAT_GRAY;
    unsigned char *buf = malloc(PNG_IMAGE_SIZE(im));
    assert_non_null(buf);
    assert_true(png_image_finish_read(&im, NULL, buf, 0, NULL));
    size_t n = (size_t)im.width * im.height, dark = 0;
    double s1 = 0, s2 = 0;
    for (size_t k = 0; k < n; k++) {
        s1 += buf[k];
        s2 += (double)buf[k] * buf[k];
        dark += buf[k] < 240;
    }
    const double nd = (double)n;
    double var = s2 / nd - (s1 / nd) * (s1 / nd);
    free(buf);
    if (var < 300.0 || dark < n / 50) {
        print_error("%s: grey variance %.1f, %zu of %zu pixels not background\n", path, var, dark, n);
        fail();
    }
#else
    (void)path;
    print_message("libpng not found at build time: pixel-variance check skipped\n");
#endif
}

static const swfs_report_range *range(const swfs_report_summary *s, const char *name)
{
    const swfs_report_range *r = swfs_report_find_range(s, name);
    if (!r) {
        print_error("no colour range '%s' in the summary\n", name);
        fail();
    }
    return r;
}

static void check_figures(const char *out, const swfs_report_summary *s, size_t expect)
{
    assert_int_equal(s->nfigures, expect);
    for (size_t k = 0; k < s->nfigures; k++) {
        char p[1024];
        snprintf(p, sizeof p, "%s/%s", out, s->figures[k].file);
        int w, h;
        png_size(p, &w, &h);
        assert_int_equal(w, s->figures[k].width);
        assert_int_equal(h, s->figures[k].height);
        assert_true(w >= 600 && h >= 400);
        check_not_blank(p);
        snprintf(p, sizeof p, "%s/%s.part", out, s->figures[k].file);
        assert_false(test_file_exists(p));
    }
}

static char *slurp(const char *path)
{
    FILE *f = fopen(path, "rb");
    assert_non_null(f);
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *s = malloc((size_t)n + 1);
    assert_int_equal(fread(s, 1, (size_t)n, f), (size_t)n);
    s[n] = '\0';
    fclose(f);
    return s;
}

static run R;

static void test_full_run(void **state)
{
    (void)state;
    if (!swfs_plot_available()) skip();
    const char *dir = test_path("report_full");
    make_run(dir, "science speckles truth pupil halo wavefront coherence", &R);
    char out[1024];
    snprintf(out, sizeof out, "%s/report", dir);
    swfs_report_summary s;
    assert_ok(swfs_report_run(dir, NULL, NULL, &s));

    /* Every figure, at its size, not blank. */
    check_figures(out, &s, 5);
    const char *names[] = {"halo.png", "focal.png", "pixel.png", "pupil.png", "coherence.png"};
    for (size_t k = 0; k < 5; k++) assert_string_equal(s.figures[k].file, names[k]);
    assert_int_equal(s.figures[0].width, 1500);
    assert_int_equal(s.figures[0].height, 440);

    /* Colour ranges are the documented robust percentiles of the data. */
    const double N = NX * NY;
    const swfs_report_range *r = range(&s, "mean_i"); /* > 100x dynamic range: log */
    double lo = pct(R.mean_i, (size_t)N, NULL, 1.0), hi = pct(R.mean_i, (size_t)N, NULL, 99.5);
    assert_true(hi / lo > 100);
    assert_true(r->log);
    double lg[NX * NY];
    for (int k = 0; k < NX * NY; k++) lg[k] = log10(R.mean_i[k]);
    assert_close(r->hi, pct(lg, (size_t)N, NULL, 99.5), 1e-9);
    assert_close(r->lo, fmax(pct(lg, (size_t)N, NULL, 1.0), r->hi - 4.0), 1e-9);
    r = range(&s, "var_i"); /* exactly 4 decades (fig:Sim-PSF-Sigma2) */
    for (int k = 0; k < NX * NY; k++) lg[k] = log10(R.var_i[k]);
    assert_true(r->log);
    assert_close(r->hi, pct(lg, (size_t)N, NULL, 99.5), 1e-9);
    assert_close(r->hi - r->lo, 4.0, 1e-12);
    r = range(&s, "halo_phase");
    assert_close(r->lo, -M_PI, 1e-12);
    assert_close(r->hi, M_PI, 1e-12);
    r = range(&s, "visib");
    assert_close(r->lo, 0.0, 0.0);
    assert_close(r->hi, 1.0, 0.0);
    r = range(&s, "gain"); /* small dynamic range: linear, valid pixels only */
    assert_false(r->log);
    double gain[NX * NY];
    for (int k = 0; k < NX * NY; k++) gain[k] = 1.0 + 0.05 * sin(0.3 * k);
    assert_close(r->lo, pct(gain, (size_t)N, R.valid, 1.0), 1e-9);
    assert_close(r->hi, pct(gain, (size_t)N, R.valid, 99.5), 1e-9);
    /* WFE, NCP and error share one symmetric range in nm: the larger of the two P99.5(|v|). */
    double aw[NPUP * NPUP], an[NPUP * NPUP];
    double mw = 0, mn = 0;
    int cnt = 0;
    for (int k = 0; k < NPUP * NPUP; k++)
        if (R.pupil[k] != 0.0) mw += R.ncp[k] + R.err[k], mn += R.ncp[k], cnt++;
    mw /= cnt, mn /= cnt;
    for (int k = 0; k < NPUP * NPUP; k++) {
        aw[k] = fabs(1e9 * (R.ncp[k] + R.err[k] - mw));
        an[k] = fabs(1e9 * (R.ncp[k] - mn));
    }
    double m = fmax(pct(aw, NPUP * NPUP, R.pupil, 99.5), pct(an, NPUP * NPUP, R.pupil, 99.5));
    r = range(&s, "wfe");
    assert_close(r->hi, m, 1e-6);
    assert_close(r->lo, -m, 1e-6);
    assert_close(range(&s, "err")->hi, m, 1e-6);
    r = range(&s, "tau0"); /* in ms */
    assert_false(r->log);
    assert_true(r->lo > 34.9 && r->hi < 55.1 && r->hi > r->lo + 5);

    /* Key numbers. */
    assert_close(s.frames, NFR, 0);
    assert_close(s.valid_fraction, 0.61, 1e-12);
    assert_close(s.median_snr, 7.25, 1e-12);
    /* The injected error map is recovered exactly, without its tilt (piston and tip/tilt
     * removed, as swfs_wfe_compare and the demo's table), to 1e-6 of itself. */
    assert_true(R.err_rms < 0.9 * R.err_rms_piston); /* the tilt matters */
    assert_close(s.err_rms, R.err_rms, 1e-6 * R.err_rms);
    assert_close(s.ncp_rms, R.ncp_rms, 1e-12);
    double wrms = 0;
    for (int k = 0; k < NPUP * NPUP; k++)
        if (R.pupil[k] != 0.0) wrms += pow(R.ncp[k] + R.err[k] - mw, 2);
    wrms = sqrt(wrms / cnt);
    assert_close(s.wfe_rms, wrms, 1e-12);
    assert_close(s.strehl, exp(-pow(2 * M_PI * wrms / LAMBDA, 2)), 1e-12);
    assert_true(s.tau0_median > 0.035 && s.tau0_median < 0.055);

    /* The intensity-vs-speckle-phase pixel: first Airy ring, valid, and the sinusoid of
     * I against arg psi peaks at arg Psi (paper Fig. 1). */
    assert_true(s.pixel_i >= 0);
    double rad = hypot(theta((int)s.pixel_i, NX), theta((int)s.pixel_j, NY));
    assert_true(rad >= 1.3 && rad <= 1.9);
    assert_true(R.valid[s.pixel_j * NX + s.pixel_i] > 0.5);
    double dphi = remainder(s.pixel_fit_phase - carg(R.halo[s.pixel_j * NX + s.pixel_i]), 2 * M_PI);
    assert_true(fabs(dphi) < 0.2);
    assert_close(s.pixel_halo_phase, carg(R.halo[s.pixel_j * NX + s.pixel_i]), 1e-12);

    /* index.html: relative image paths, the key numbers as text, no .part left. */
    char *html = slurp(s.html);
    for (size_t k = 0; k < 5; k++) {
        char needle[64];
        snprintf(needle, sizeof needle, "src=\"%s\"", names[k]);
        assert_non_null(strstr(html, needle));
    }
    char num[64];
    snprintf(num, sizeof num, "%.1f nm rms", 1e9 * R.err_rms);
    assert_non_null(strstr(html, num));
    assert_non_null(strstr(html, "<td id=\"frames\">240</td>"));
    assert_non_null(strstr(html, "61.0 %"));
    assert_non_null(strstr(html, "7.25"));
    assert_null(strstr(html, "skipped"));
    free(html);
    snprintf(out, sizeof out, "%s/report/index.html.part", dir);
    assert_false(test_file_exists(out));
}

/* A wavefront product from which pupil took the AO residual's time mean out: its own panel
 * (five with the truth's two: three rows), named in the caption. */
static void test_resmean_panel(void **state)
{
    (void)state;
    if (!swfs_plot_available()) skip();
    const char *dir = test_path("report_resmean");
    run r;
    make_run(dir, "truth pupil wavefront resmean", &r);
    swfs_report_summary s;
    assert_ok(swfs_report_run(dir, NULL, NULL, &s));
    int found = 0;
    for (size_t k = 0; k < s.nfigures; k++)
        if (!strcmp(s.figures[k].file, "pupil.png")) {
            found = 1;
            assert_int_equal(s.figures[k].height, 3 * 880 / 2);
        }
    assert_true(found);
    char *html = slurp(s.html);
    assert_non_null(strstr(html, "time mean that the telemetry measured"));
    free(html);
}

/* Only the raw cubes: moments computed from them, the pixel figure still drawn, notes
 * for everything else, and the pixel chosen by speckle power. */
static void test_cubes_only(void **state)
{
    (void)state;
    if (!swfs_plot_available()) skip();
    const char *dir = test_path("report_cubes");
    run r;
    make_run(dir, "science speckles", &r);
    const char *out = test_path("report_cubes_out/nested");
    swfs_report_summary s;
    swfs_report_options o;
    swfs_report_options_default(&o);
    o.pct_lo = 5.0;
    o.pct_hi = 95.0;
    assert_ok(swfs_report_run(dir, out, &o, &s));
    check_figures(out, &s, 2);
    assert_string_equal(s.figures[0].file, "focal.png");
    assert_string_equal(s.figures[1].file, "pixel.png");
    assert_null(swfs_report_find_range(&s, "gain"));
    assert_close(s.frames, NFR, 0);
    assert_true(isnan(s.valid_fraction) && isnan(s.wfe_rms));
    /* Mean speckle power range from the cube: within sampling error of the truth's P5/P95. */
    const swfs_report_range *rs = range(&s, "mean_sp");
    double lo = pct(r.sig2, NX * NY, NULL, 5.0), hi = pct(r.sig2, NX * NY, NULL, 95.0);
    double elo = rs->log ? pow(10, rs->lo) : rs->lo, ehi = rs->log ? pow(10, rs->hi) : rs->hi;
    assert_true(fabs(elo / lo - 1) < 0.2 && fabs(ehi / hi - 1) < 0.2);
    assert_true(s.nnotes >= 3);
    char *html = slurp(s.html);
    assert_non_null(strstr(html, "halo.fits not found"));
    assert_non_null(strstr(html, "wavefront.fits not found"));
    free(html);
}

static void test_bad_inputs(void **state)
{
    (void)state;
    swfs_report_summary s;
    assert_int_equal(swfs_report_run(test_path("no_such_run"), NULL, NULL, &s), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "no_such_run"));

    const char *dir = test_path("report_bad");
    mkdir(dir, 0777);
    char stale[1024]; /* a page left by an earlier run of this test must not count */
    snprintf(stale, sizeof stale, "%s/report/index.html", dir);
    remove(stale);
    swfs_report_options o;
    swfs_report_options_default(&o);
    o.pct_lo = 50;
    o.pct_hi = 10;
    assert_int_equal(swfs_report_run(dir, NULL, &o, &s), SWFS_ERR_ARG);

    /* A halo.fits that is not FITS: an error naming it, not a silent skip. */
    char p[1024];
    snprintf(p, sizeof p, "%s/halo.fits", dir);
    FILE *f = fopen(p, "wb");
    fputs("not a FITS file", f);
    fclose(f);
    assert_int_not_equal(swfs_report_run(dir, NULL, NULL, &s), 0);
    assert_non_null(strstr(swfs_last_error(), "halo.fits"));
    remove(p);

    /* An empty run folder: an error naming it and what was looked for, and no page. */
    assert_int_equal(swfs_report_run(dir, NULL, NULL, &s), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "report_bad: nothing to report"));
    assert_non_null(strstr(swfs_last_error(), "halo.fits"));
    snprintf(p, sizeof p, "%s/report/index.html", dir);
    assert_false(test_file_exists(p));
    /* truth.fits and pupil.fits alone draw nothing either. */
    run r0;
    make_run(dir, "truth pupil", &r0);
    assert_int_equal(swfs_report_run(dir, NULL, NULL, &s), SWFS_ERR_IO);
    assert_false(test_file_exists(p));

    /* A pixel outside the grid is refused. */
    run r;
    const char *d2 = test_path("report_badpix");
    make_run(d2, "halo", &r);
    swfs_report_options_default(&o);
    o.pixel_i = NX;
    o.pixel_j = 3;
    assert_int_equal(swfs_report_run(d2, NULL, &o, &s), SWFS_ERR_ARG);
}

static void write_bytes(const char *path, const unsigned char *b, size_t n)
{
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(b, 1, n, f), n);
    fclose(f);
}

/* A PNG is complete only from its signature to an IEND chunk that ends the file; a report
 * whose figures are cut short (a file-size limit, as a full disk) fails and leaves no PNG. */
static void test_png_complete(void **state)
{
    (void)state;
    if (!swfs_plot_available()) skip();
    const char *dir = test_path("report_png");
    run r;
    make_run(dir, "halo", &r);
    swfs_report_summary s;
    assert_ok(swfs_report_run(dir, NULL, NULL, &s));
    char png[1024], cut[1024];
    snprintf(png, sizeof png, "%s/report/halo.png", dir);
    snprintf(cut, sizeof cut, "%s/cut.png", dir);
    char *full = slurp(png);
    FILE *f = fopen(png, "rb");
    fseek(f, 0, SEEK_END);
    size_t n = (size_t)ftell(f);
    fclose(f);
    assert_ok(swfs_plot_png_check(png));
    const size_t cuts[] = {0, 7, 8, 20, 33, n / 2, n - 12, n - 5, n - 1};
    for (size_t k = 0; k < sizeof cuts / sizeof cuts[0]; k++) {
        write_bytes(cut, (const unsigned char *)full, cuts[k]);
        assert_int_not_equal(swfs_plot_png_check(cut), SWFS_OK);
        assert_non_null(strstr(swfs_last_error(), "cut.png"));
    }
    unsigned char *more = malloc(n + 3);
    memcpy(more, full, n);
    memcpy(more + n, "xyz", 3);
    write_bytes(cut, more, n + 3);
    assert_int_not_equal(swfs_plot_png_check(cut), SWFS_OK);
    assert_non_null(strstr(swfs_last_error(), "3 bytes after its IEND"));
    free(more);
    free(full);

    /* Figures written under a 30 kB file-size limit: the run fails, nothing truncated stays. */
    char out[512];
    snprintf(out, sizeof out, "%s/limited", dir);
    const char *leftovers[] = {"halo.png", "focal.png", "index.html"}; /* of an earlier run */
    for (size_t k = 0; k < 3; k++) {
        snprintf(png, sizeof png, "%s/%s", out, leftovers[k]);
        remove(png);
    }
    pid_t pid = fork();
    assert_true(pid >= 0);
    if (pid == 0) {
        signal(SIGXFSZ, SIG_IGN);
        struct rlimit rl = {30000, 30000};
        setrlimit(RLIMIT_FSIZE, &rl);
        swfs_report_summary s2;
        int rc = swfs_report_run(dir, out, NULL, &s2);
        _exit(rc != SWFS_OK && strstr(swfs_last_error(), "halo.png") ? 0 : 1);
    }
    int st = 0;
    waitpid(pid, &st, 0);
    assert_true(WIFEXITED(st));
    assert_int_equal(WEXITSTATUS(st), 0);
    snprintf(png, sizeof png, "%s/halo.png", out);
    assert_false(test_file_exists(png));
    snprintf(png, sizeof png, "%s/halo.png.part", out);
    assert_false(test_file_exists(png));
}

/* Headless Chromium loads index.html and every image in it. */
static void test_chromium(void **state)
{
    (void)state;
    if (!swfs_plot_available()) skip();
    FILE *w = popen("command -v chromium 2>/dev/null", "r");
    char exe[512] = "";
    if (w) {
        if (!fgets(exe, sizeof exe, w)) exe[0] = '\0';
        pclose(w);
    }
    exe[strcspn(exe, "\n")] = '\0';
    if (!exe[0]) {
        print_message("chromium is not on PATH: browser check skipped (Debian: apt-get install chromium)\n");
        skip();
    }
    const char *dir = test_path("report_browser");
    run r;
    make_run(dir, "science speckles truth pupil halo wavefront coherence", &r);
    swfs_report_summary s;
    assert_ok(swfs_report_run(dir, NULL, NULL, &s));
    assert_int_equal(s.nfigures, 5);
    char cmd[12288];
    snprintf(cmd, sizeof cmd,
             "'%s' --headless --no-sandbox --disable-gpu --disable-background-networking --no-first-run "
             "--disable-dev-shm-usage --user-data-dir='%s' --virtual-time-budget=5000 --dump-dom 'file://%s' "
             "2>/dev/null",
             exe, test_path("report_browser_profile"), s.html);
    FILE *c = popen(cmd, "r");
    assert_non_null(c);
    size_t cap = 1 << 16, len = 0;
    char *dom = malloc(cap);
    size_t got;
    while ((got = fread(dom + len, 1, cap - len - 1, c)) > 0) {
        len += got;
        if (len + 1 >= cap) dom = realloc(dom, cap *= 2);
    }
    dom[len] = '\0';
    pclose(c);
    char want[96];
    snprintf(want, sizeof want, "data-images-ok=\"%zu\"", s.nfigures);
    if (!strstr(dom, want) || !strstr(dom, "data-images-total=\"5\"")) {
        char *b = strstr(dom, "<body");
        print_error("chromium did not load every image; body: %.200s\n", b ? b : dom);
        free(dom);
        fail();
    }
    free(dom);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_full_run),
        cmocka_unit_test(test_resmean_panel),
        cmocka_unit_test(test_cubes_only),
        cmocka_unit_test(test_bad_inputs),
        cmocka_unit_test(test_png_complete),
        cmocka_unit_test(test_chromium),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
