# lib_systems.sh's second system, sh24-base (24 x 24 Shack-Hartmann, 6 WFS frames per camera
# frame, 10 m/s wind, 0.1 lambda/D vibration, read noise 10 counts): seed 1 with the taught
# default; under the sanitizers seed 2 with --recon vk, which must meet the bounds or say
# that the joint fit took no step (lib_systems.sh). The bound: 2.5 x the full-size table's
# ideal-speckle error (13.2 nm).
# usage: bash cli_systems_sh24.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_systems.sh"
systems_setup "$@"
if [ -n "$taught" ]; then
    run_system sh24-base 24 6.0 10 60 0.1 15 10 33 1 300.637
else
    run_system sh24-base 24 6.0 10 60 0.1 15 10 33 2 300.274
fi
echo "cli_systems_sh24: ok"
