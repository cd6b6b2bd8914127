#include "cli.h"
#include <stdio.h>
/* PLACEHOLDER while the command is being written: not part of any commit. */
int swfs_cmd_estimate(int argc, char **argv) { (void)argc; (void)argv; fprintf(stderr, "specklewfs estimate: not built yet\n"); return CLI_FAIL; }
