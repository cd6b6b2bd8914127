# Shared by cli_learn.sh and cli_teach.sh (sourced, not run: its name keeps it out of the
# cli_*.sh test list): the observation both learn and teach for, on a small system (my.conf:
# config/small-loop.conf, the 12 x 12 Shack-Hartmann of 217 actuators on a 66-sample pupil, 3
# cubes of 60 camera frames; two layers at 15 / 22 m/s, its own seed), reduced and synced, in
# the scratch dir, which learn_setup makes the working folder.
. "$(dirname "${BASH_SOURCE[0]}")/lib_cli.sh"
learn_setup() { # learn_setup <specklewfs> <scratch dir>
    cli_setup "$@"
    cd "$D" || fail "cd $D"
    cp "$(dirname "${BASH_SOURCE[0]}")/../config/small-loop.conf" my.conf || fail "config/small-loop.conf"
    "$B" simulate my.conf layer_speed=15,22 vib_amp=0.3 seed=9 export_modal=1 -o obs --quiet > /dev/null 2>&1 || fail "simulate obs"
    "$B" reduce obs/raw_000.fits obs/raw_001.fits obs/raw_002.fits --dark obs/dark.fits --flat obs/flat.fits \
        -o science.fits 2> reduce.log || fail "reduce"
    "$B" sync science.fits obs/handshake.log -o timing.txt --ratio-min 5 --ratio-max 8 > sync.log || fail "sync"
    cp obs/actuators.fits actuators.fits
    cp obs/valid.fits valid.fits
    cp obs/pupil.fits pupil.fits
    cp obs/slopes_0*.fits .  # the observation's telemetry, as the recipe's `wind` reads it
}
# ncp_with MAP TAG TIMING [speckles options]: the whole path with a taught map (speckles --recon
# MAP, estimate, pupil --truth; files *_TAG), the NCP error [nm] on stdout
ncp_with() {
    local map=$1 tag=$2 timing=$3
    shift 3
    "$B" speckles "$timing" --science science.fits --actuators actuators.fits --recon "$map" "$@" --match science.fits \
        "sci_$tag.fits" -o "spk_$tag.fits" 2> "speckles_$tag.log" || { cat "speckles_$tag.log" >&2; fail "speckles ($map)"; }
    "$B" estimate "sci_$tag.fits" "spk_$tag.fits" -o "halo_$tag.fits" > /dev/null 2>&1 || fail "estimate ($map)"
    "$B" pupil "halo_$tag.fits" -o "pupil_$tag.fits" --truth obs/truth.fits > "pupil_$tag.log" || fail "pupil ($map)"
    ncp_error "pupil_$tag.log"
}
# teach_files: teach with no description at all, the system from the observation's own files
# (the science cube's geometry, the DM, the pupil), the rest the simulator's defaults; its two
# layers and modal filter, and the loops' slope noise measured from the slopes; sets etf, the
# NCP error through the whole path with that map (taught_f.fits, its loops in taught_f/)
teach_files() {
    "$B" teach obs/slopes_0*.fits --science science.fits --actuators actuators.fits --pupil pupil.fits -o taught_f.fits \
        --work taught_f --loops 4 --max-loops 4 > teach_f.log 2>&1 || { cat teach_f.log; fail "teach from the observation's files"; }
    grep -q "2 frozen-flow layers" teach_f.log && grep -q "ao_modes = 5[3-9]$" teach_f.log \
        || { cat teach_f.log; fail "teach from files: two layers and the modal filter expected"; }
    # the loops' slope noise is the observation's white slope noise, measured from its slopes (the
    # simulator's 3e-8 rad rms; measured 3.0e-8), a small share of the slopes' variance (under
    # 5 %), in the map's header too
    awk '/the slopes. white noise/ { for (i = 1; i <= NF; i++) { if ($i == "noise") v = $(i + 1) + 0;
        if ($i == "%" && $(i + 1) == "of") p = $(i - 1) + 0 } }
        END { exit !(v > 2.7e-8 && v < 3.3e-8 && p > 0 && p < 5) }' teach_f.log && grep -q "the loops' slope_noise [0-9.e-]* rad, the same$" teach_f.log \
        || { grep "white noise" teach_f.log; fail "teach: the white slope noise (3e-8) expected"; }
    head -c 14400 taught_f.fits | grep -aq "TEACHNOI=" || fail "teach: TEACHNOI expected in the map's header"
    # the modal filter from the slopes (the observation's loop controls the simulator's 56
    # modes; within 3 above), its calibration loops kept in modes_NN/, and the profiles it was
    # read from: modes.tsv (a row per mode after piston, the observation, the calibration loop
    # and each zonal loop) and modes.png
    head -c 11520 taught_f.fits | grep -aq "TEACHMSR= 'slopes" && [ -d taught_f/modes_00 ] \
        || fail "teach: TEACHMSR = 'slopes' and a calibration loop expected"
    head -1 taught_f/modes.tsv | grep -q "^# mode	observation	loop_5[3-9]	zonal_0.02	zonal_0.03	zonal_0.05	zonal_0.07	zonal_0.1	zonal_0.2$" \
        && [ "$(grep -vc '^#' taught_f/modes.tsv)" -gt 150 ] && [ -s taught_f/modes.png ] \
        || { head -3 taught_f/modes.tsv; fail "teach: modes.tsv / modes.png"; }
    etf=$(ncp_with taught_f.fits tf timing.txt)
}
