/* specklewfs replay: the inputs of `stream` (timing table, telemetry, reduced science
 * cube) published into ImageStreamIO shared-memory streams at the WFS rate, for tests
 * and demos of `live` (live.h: swfs_replay_run). */
#include "cli.h"

#include "specklewfs/live.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs replay --timing TIMING.txt --science SCIENCE.fits [--slopes DIR|FILE]\n"
    "                         [--shm-dir DIR] [--wfs-name NAME] [--camera-name NAME] [options]\n"
    "       specklewfs replay --wfs-log DIR|FILE --science SCIENCE.fits [--shm-dir DIR] [--wfs-name NAME]\n"
    "                         [--camera-name NAME] [--speed F] [--depth N] [--wait-reader T] [--remove]\n"
    "\n"
    "Publishes WFS telemetry and camera frames into two shared-memory streams (ImageStreamIO\n"
    "2.00) as an AO system would: every WFS row at its time ((row + 1) / rate: a stamp marks\n"
    "the end of its frame), every camera frame at the end of its exposure from the timing\n"
    "table (cube start + (j + 1) x ratio WFS frames), in time order, at the real WFS rate or\n"
    "--speed times faster. Cubes marked 'straddles' are published too (a stream has no file\n"
    "boundaries). Telemetry files are placed by their FRAME0 keyword (the simulator's), else\n"
    "one after the other in the order the table names them.\n"
    "\n"
    "  --timing, --science, --slopes   as for 'specklewfs stream'\n"
    "  --wfs-log DIR|FILE    instead of --timing: a WFS milk log (as 'stream --wfs-log'), published\n"
    "                        with its own stamps and lost frames, and the science cube's frames at\n"
    "                        their STAMPS (reduce of camera logs): live then sees exactly what\n"
    "                        'stream --wfs-log' reads\n"
    "  --shm-dir DIR         stream folder (default $MILK_SHM_DIR, /milk/shm, /dev/shm, /tmp)\n"
    "  --wfs-name NAME       WFS stream (default swfs_wfs)\n"
    "  --camera-name NAME    camera stream (default swfs_camera)\n"
    "  --wfs-rate HZ         WFS frame rate (default: WFSRATE of the telemetry)\n"
    "  --speed F             publish F times faster than real time (default 1)\n"
    "  --drop-wfs P, --drop-camera P   lose each frame with probability P (the counter moves\n"
    "                        on, as when a reader misses it; never the last frame)\n"
    "  --jitter S            Gaussian jitter [s rms] of the time stamps and publication times\n"
    "  --seed N              for drops and jitter (default 1)\n"
    "  --depth N             temporal rolling buffers of N frames (default: 2-D streams)\n"
    "  --wait-reader T       first wait up to T s for a reader on both streams (and again after\n"
    "                        a restart); an error if none comes\n"
    "  --restart-after N     re-create both streams (a writer restart) after every N WFS frames\n"
    "  --drop-log FILE       list the frames lost on purpose\n"
    "  --remove              remove the streams at the end (default: leave them)\n";

int swfs_cmd_replay(int argc, char **argv)
{
    const char *cmd = "replay";
    swfs_replay_options o;
    swfs_replay_options_default(&o);
    long seed = 1, depth = 0, restart = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], **str = NULL;
        long *lv = NULL;
        double *dv = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "--timing")) str = &o.timing;
        else if (!strcmp(a, "--wfs-log")) str = &o.wfs_log;
        else if (!strcmp(a, "--science")) str = &o.science;
        else if (!strcmp(a, "--slopes")) str = &o.slopes;
        else if (!strcmp(a, "--shm-dir")) str = &o.dir;
        else if (!strcmp(a, "--wfs-name")) str = &o.wfs_name;
        else if (!strcmp(a, "--camera-name")) str = &o.camera_name;
        else if (!strcmp(a, "--drop-log")) str = &o.drop_log;
        else if (!strcmp(a, "--wfs-rate")) dv = &o.wfs_rate;
        else if (!strcmp(a, "--speed")) dv = &o.speed;
        else if (!strcmp(a, "--drop-wfs")) dv = &o.drop_wfs;
        else if (!strcmp(a, "--drop-camera")) dv = &o.drop_camera;
        else if (!strcmp(a, "--jitter")) dv = &o.jitter;
        else if (!strcmp(a, "--wait-reader")) dv = &o.wait_reader;
        else if (!strcmp(a, "--seed")) lv = &seed;
        else if (!strcmp(a, "--depth")) lv = &depth;
        else if (!strcmp(a, "--restart-after")) lv = &restart;
        else if (!strcmp(a, "--remove")) { o.remove = 1; continue; }
        else return cli_usage_error(cmd, "unknown argument '%s'", a);
        const char *v = i + 1 < argc ? argv[++i] : NULL;
        if (str) {
            if (!v) return cli_usage_error(cmd, "%s needs a value", a);
            *str = v;
        } else if (lv ? cli_parse_long(cmd, a, v, lv) : cli_parse_double(cmd, a, v, dv)) {
            return CLI_USAGE;
        }
    }
    if (!(o.timing || o.wfs_log) || !o.science) return cli_usage_error(cmd, "needs --timing (or --wfs-log) and --science");
    if (o.wfs_log && (o.timing || o.slopes))
        return cli_usage_error(cmd, "--wfs-log publishes a milk log with its own stamps: no --timing or --slopes");
    if (o.wfs_log && (o.drop_wfs > 0 || o.drop_camera > 0 || o.jitter > 0 || restart || o.wfs_rate > 0))
        return cli_usage_error(cmd, "--wfs-log publishes the log as it was: no --drop-wfs, --drop-camera, --jitter, "
                               "--restart-after or --wfs-rate");
    if (!(o.speed > 0)) return cli_usage_error(cmd, "--speed must be > 0, got %g", o.speed);
    if (!(o.drop_wfs >= 0 && o.drop_wfs < 1) || !(o.drop_camera >= 0 && o.drop_camera < 1))
        return cli_usage_error(cmd, "--drop-wfs and --drop-camera must be in [0, 1)");
    if (!(o.jitter >= 0) || !(o.wfs_rate >= 0) || !(o.wait_reader >= 0))
        return cli_usage_error(cmd, "--jitter, --wfs-rate and --wait-reader must be >= 0");
    if (seed < 0 || depth < 0 || depth > 100000 || restart < 0)
        return cli_usage_error(cmd, "--seed, --depth (<= 100000) and --restart-after must be >= 0");
    o.seed = (uint64_t)seed;
    o.depth = (size_t)depth;
    o.restart_after = (size_t)restart;
    swfs_replay_result r;
    if (swfs_replay_run(&o, &r)) return cli_error(cmd);
    printf("replay: %zu WFS frames (%zu lost) at %.1f Hz and %zu camera frames (%zu lost, %.4g WFS frames each) in %.2f s"
           "; %zu restarts; latest publication %.2f ms after its time\n",
           r.wfs_frames, r.wfs_dropped, r.wfs_rate, r.camera_frames, r.camera_dropped, r.ratio, r.seconds, r.restarts,
           1e3 * r.late_max);
    return CLI_OK;
}
