# lib_systems.sh's first system, sh16-issue (16 x 16 Shack-Hartmann, 9.7 WFS frames per
# camera frame, 14 m/s wind, 0.4 lambda/D vibration, read noise 15 counts), seed 1: the whole
# default path within 1.3x of the ideal speckles (under the sanitizers: --recon vk and the
# other bounds). The bound: 2.5 x the full-size table's ideal-speckle error (10.4 nm).
# usage: bash cli_systems_sh16.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_systems.sh"
systems_setup "$@"
run_system sh16-issue 16 9.7 14 200 0.4 12 15 26 1 300.637
echo "cli_systems_sh16: ok"
