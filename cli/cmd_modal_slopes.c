/* specklewfs modal-slopes MODAL.fits... --cm CM.fits|--imat RM.fits -o DIR: a modal system's
 * coefficients back to its Shack-Hartmann's slopes (run.h swfs_modal_slopes_run). */
#include "cli.h"

#include "specklewfs/run.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

static const char *usage_text =
    "usage: specklewfs modal-slopes MODAL.fits... (--cm CM.fits | --imat RM.fits) -o DIR\n"
    "\n"
    "A modal AO system logs per WFS frame the coefficients c = CM s of its WFS's slopes s\n"
    "(cacao's modevalWFS through CMmodesWFS). Where that WFS is a Shack-Hartmann and CM is known,\n"
    "this writes s' = CM+ c, the slopes projected onto CM's row space (the minimum-norm slopes\n"
    "that give c), as telemetry the Shack-Hartmann path takes: sync, then speckles with\n"
    "--actuators, --valid and --pupil, whose default teaches a map for the observation\n"
    "(docs/telemetry.md, \"The modal input kind\"). The linear model (speckles --basis) takes the\n"
    "coefficients themselves but cannot teach.\n"
    "\n"
    "  MODAL.fits...  coefficient files (coefficients x WFS frames)\n"
    "  --cm CM.fits   the modal control matrix: NAXIS1 = the slopes (x of the valid\n"
    "                 subapertures, then y, as --valid orders them), NAXIS2 = the coefficients,\n"
    "                 in the files' units per radian (simulate export_modal=1: cm_modes.fits)\n"
    "  --imat RM.fits instead of CM: the modal response matrix, each mode's slopes per unit\n"
    "                 coefficient (NAXIS1 = the coefficients, NAXIS2 = the slopes; simulate\n"
    "                 export_modal=1: rm_modes.fits). Then s' = RM c, and the control matrix\n"
    "                 taken is RM's pseudo-inverse, written as pinv_RM.fits: exact where the\n"
    "                 system's CM inverts RM on its modes (least squares, a truncated SVD), close\n"
    "                 where it regularizes them (docs/telemetry.md)\n"
    "  -o DIR         an existing folder, not the inputs': each file under its own name, with\n"
    "                 BUNIT 'rad' and the input's WFSRATE and FRAME0, and a copy of CM.fits\n"
    "                 (or pinv_RM.fits), which their MODALCM key names (teach then learns its loops' slopes on the\n"
    "                 same projection); all files or none\n"
    "Prints CM's rank and condition, the frames written, and the share of the coefficients CM\n"
    "cannot have made (0 where its rank is its number of coefficients). With --imat it checks\n"
    "that the coefficients carry the white noise a least-squares CM of RM gives each mode, and\n"
    "warns where they do not (a regularizing CM: then give --cm).\n";

int swfs_cmd_modal_slopes(int argc, char **argv)
{
    const char *cmd = "modal-slopes";
    swfs_modal_slopes_options o = {0};
    const char **files = calloc((size_t)argc, sizeof *files);
    size_t nf = 0;
    if (!files) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const cli_opt opts[] = {
        {"--cm", CLI_STRING, &o.cm, "a file name", 0},
        {"--imat", CLI_STRING, &o.imat, "a file name", 0},
        {"-o", CLI_STRING, &o.outdir, "a folder", 0},
    };
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, NULL, NULL, files, &nf};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc) { free(files); return rc < 0 ? CLI_OK : rc; }
    if (!nf) rc = cli_usage_error(cmd, "needs at least one coefficient file");
    else if (!o.cm && !o.imat)
        rc = cli_usage_error(cmd, "needs --cm CM.fits (the modal control matrix) or --imat RM.fits (the modal response matrix)");
    else if (o.cm && o.imat) rc = cli_usage_error(cmd, "takes --cm or --imat, not both");
    else if (!o.outdir) rc = cli_usage_error(cmd, "needs -o DIR (an existing folder)");
    if (rc) { free(files); return rc; }
    o.files = files;
    o.nfiles = nf;
    swfs_modal_slopes_result r;
    rc = swfs_modal_slopes_run(&o, &r);
    free(files);
    if (rc) return cli_error(cmd);
    if (o.cm)
        printf("modal-slopes: %zu coefficients -> %zu slopes through the pseudo-inverse of %s (rank %zu, condition %.3g)\n",
               r.ncoef, r.nslopes, o.cm, r.rank, r.cond);
    else
        printf("modal-slopes: %zu coefficients -> %zu slopes through the response matrix %s (rank %zu, condition %.3g)\n",
               r.ncoef, r.nslopes, o.imat, r.rank, r.cond);
    printf("modal-slopes: %zu WFS frames in %zu files -> %s/; the coefficients CM cannot have made: %.2g of their rms\n",
           r.nframes, nf, o.outdir, r.resid);
    if (o.imat && r.lsq_ratio == 0)
        printf("modal-slopes: the coefficients carry no white noise in the modes a least-squares CM of the response "
               "matrix makes the noisiest\n");
    else if (o.imat && !isnan(r.lsq_ratio))
        printf("modal-slopes: the coefficients' white noise, poorly sensed modes against well-sensed ones, over what a "
               "least-squares CM of the response matrix gives: %.3g (1 for such a CM)\n", r.lsq_ratio);
    else if (o.imat)
        printf("modal-slopes: too few frames or coefficients to check how the coefficients were made\n");
    if (r.lsq_warns)
        fprintf(stderr, "specklewfs modal-slopes: warning: the coefficients' white noise is not what a least-squares "
                "control matrix of %s gives them (%.3g, outside %.2g-%.2g): the system's control matrix regularizes its "
                "modes, so RM c is not the slopes' projection and teach's map will not fit them; give the system's "
                "control matrix (--cm), or take the coefficients through the linear model (speckles --basis)\n",
                o.imat, r.lsq_ratio, SWFS_MODAL_LSQ_RATIO_MIN, 1 / SWFS_MODAL_LSQ_RATIO_MIN);
    return CLI_OK;
}
