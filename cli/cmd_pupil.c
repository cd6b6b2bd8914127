#include "cli.h"
#include <stdio.h>
/* PLACEHOLDER while the command is being written: not part of any commit. */
int swfs_cmd_pupil(int argc, char **argv) { (void)argc; (void)argv; fprintf(stderr, "specklewfs pupil: not built yet\n"); return CLI_FAIL; }
