#include "cli.h"
#include <stdio.h>
/* PLACEHOLDER while the command is being written: not part of any commit. */
int swfs_cmd_simulate(int argc, char **argv) { (void)argc; (void)argv; fprintf(stderr, "specklewfs simulate: not built yet\n"); return CLI_FAIL; }
