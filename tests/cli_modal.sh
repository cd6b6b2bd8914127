# Telemetry of any AO system through the generic linear model (--basis): the time-series
# simulation exported in the forms other systems log (simulate export_modal=1) --
#   modal: cacao-style WFS-measured modal coefficients [um of DM surface] of unit-rms mode
#          shapes on a DM grid that is offset, turned by 10 degrees and mirrored on the pupil;
#   control: valid-only slopes, an external control matrix into actuator space and the
#          actuators' influence functions on the pupil grid --
# recovers the NCP as the native Shack-Hartmann path does on the same frames (within 10 %);
# the registration matters (unmirrored: worse); wrong units, shapes and grids are refused
# naming the file and the value, with no output left; `stream --basis` runs the same model, and
# `live` on the modal stream that `replay` publishes too. Measured: 23.0 nm native, 22.7 modal,
# 22.7 control, 22.7 stream, 22.7 live (1135 nm with the mirror left out); the valid-only
# slopes with the valid-subaperture map 23.0 nm, as native. An --imat of lower rank than its
# basis functions (columns repeated) runs, and the summary notes its rank.
# usage: bash cli_modal.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
SPK_RECON=(--recon vk) # the von Karman map: this test is not about the reconstructor
S="$D/sim"
"$B" simulate mode=timeseries --quiet -o "$S" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=60 cube_gap=150 \
    layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 seed=1 export_modal=1 export_truth=1 > "$D/sim.log" 2>&1 \
    || { cat "$D/sim.log"; fail "simulate"; }
reg=$(sed -n 's/.*--basis with \(.*\) --coef-scale.*/\1/p' "$D/sim.log")
[ -n "$reg" ] || { cat "$D/sim.log"; fail "simulate printed no registration"; }
reduce_sync "$D" --ratio-min 5 --ratio-max 8
native=$(speckles_pupil "$D")
# pupil --truth prints, beside the NCP error, the error with the AO residual's time mean left in
# the wavefront (the halo's RESMEAN put back): what --keep-resmean gives from the same fit
"$B" pupil "$D/halo.fits" -o "$D/pupil_k.fits" --truth "$S/truth.fits" --keep-resmean > "$D/pupil_k.log" \
    || fail "pupil --keep-resmean"
kept=$(ncp_error_kept "$D/pupil.log")
grep -q "^  mean kept" "$D/pupil.log" && [ -n "$kept" ] && [ "$kept" = "$(ncp_error "$D/pupil_k.log")" ] \
    && ! grep -q "^  mean kept" "$D/pupil_k.log" \
    || { cat "$D/pupil.log" "$D/pupil_k.log"; fail "the mean-kept error $kept nm against --keep-resmean's"; }
# The modal telemetry times itself: sync correlates the star's track with the Z-tilt of the
# model's wavefront (the handshake log names the modal files).
sed "s#slopes_#modal_#" "$S/handshake.log" > "$S/handshake_modal.log"
# shellcheck disable=SC2086
"$B" sync "$D/science.fits" "$S/handshake_modal.log" -o "$D/timing_modal.txt" --ratio-min 5 --ratio-max 8 \
    --basis "$S/dm_modes.fits" $reg --coef-scale 2e-6 > "$D/sync_modal.log" || { cat "$D/sync_modal.log"; fail "sync --basis"; }
r0=$(awk '/^ratio/ { print $2 }' "$D/timing.txt"); r1=$(awk '/^ratio/ { print $2 }' "$D/timing_modal.txt")
l0=$(awk '/^lag/ { print $2 }' "$D/timing.txt"); l1=$(awk '/^lag/ { print $2 }' "$D/timing_modal.txt")
echo "cli_modal: sync on slopes: ratio $r0, lag $l0; on the modal coefficients: ratio $r1, lag $l1" >&2
awk -v a="$r0" -v b="$r1" -v c="$l0" -v d="$l1" 'BEGIN { exit !(a - b < 0.01 && b - a < 0.01 && c - d < 0.2 && d - c < 0.2) }' \
    || fail "sync --basis: ratio $r1, lag $l1 against $r0, $l0 from the slopes"
sed "s#/slopes_#/slopes_valid_#" "$D/timing.txt" > "$D/timing_valid.txt"
linear() { # linear <name> <timing> <speckles options...>: prints the NCP error
    local n=$1 t=$2; shift 2
    # shellcheck disable=SC2086
    "$B" speckles "$t" --science "$D/science.fits" "$@" -o "$D/sp_$n.fits" --match "$D/science.fits" "$D/sci_$n.fits" \
        2> "$D/speckles_$n.log" || { cat "$D/speckles_$n.log"; fail "$n: speckles"; }
    "$B" estimate "$D/sci_$n.fits" "$D/sp_$n.fits" -o "$D/halo_$n.fits" > /dev/null 2>&1 || fail "$n: estimate"
    "$B" pupil "$D/halo_$n.fits" -o "$D/pupil_$n.fits" --truth "$S/truth.fits" > "$D/pupil_$n.log" || fail "$n: pupil"
    ncp_error "$D/pupil_$n.log"
}
# shellcheck disable=SC2086
modal=$(linear modal "$D/timing_modal.txt" --basis "$S/dm_modes.fits" $reg --coef-scale 2e-6)
control=$(linear control "$D/timing_valid.txt" --basis "$S/influence.fits" --control "$S/control.fits")
# The same valid-only slopes through the Shack-Hartmann model with the AO system's
# valid-subaperture map: the native path's numbers, its reconstructor in the narrow layout.
valid=$(linear valid "$D/timing_valid.txt" --actuators "$S/actuators.fits" --valid "$S/valid.fits" --recon vk \
    --write-recon "$D/recon_valid.fits")
"$B" stream --timing "$D/timing_valid.txt" --science "$D/science.fits" --recon "$D/recon_valid.fits" \
    --actuators "$S/actuators.fits" --valid "$S/valid.fits" -o "$D/halo_svalid.fits" > "$D/stream_valid.log" 2>&1 \
    || { cat "$D/stream_valid.log"; fail "stream --valid"; }
"$B" pupil "$D/halo_svalid.fits" -o "$D/pupil_svalid.fits" --truth "$S/truth.fits" > "$D/pupil_svalid.log" || fail "pupil"
svalid=$(ncp_error "$D/pupil_svalid.log")
echo "cli_modal: valid-only slopes with --valid: speckles $valid nm, stream $svalid nm (native $native nm)" >&2
awk -v a="$valid" -v b="$native" 'BEGIN { exit !(a == b) }' || fail "--valid: $valid nm against $native nm native"
awk -v a="$svalid" -v b="$native" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "stream --valid: $svalid nm"
# modal-slopes: the modal coefficients through the modal control matrix's pseudo-inverse are
# valid-only slopes again (CM's 216 modes span 216 of the 224 slope directions: the slopes'
# projection, within 15 % of them in rms; measured 8 %), and the Shack-Hartmann path with the
# valid map takes them, its default teaching a map from them (four loops here, for the suite's
# time; their slopes projected as the telemetry was, which modal-slopes' MODALCM key tells
# teach; the DM told, the simulation's interpolated surface, which the default's choice by the
# science frames keeps here to the same speckles: one map taught, not two): within 10 % of the
# native NCP error. (vk is no choice there: the projection leaves no slope outside the modes'
# span, from which vk estimates the noise, and its map without noise gave 297 nm.)
mkdir -p "$D/unproj"
"$B" modal-slopes "$S"/modal_0*.fits --cm "$S/cm_modes.fits" -o "$D/unproj" > "$D/modal_slopes.log" 2>&1 \
    || { cat "$D/modal_slopes.log"; fail "modal-slopes"; }
grep -q "216 coefficients -> 224 slopes .* (rank 216," "$D/modal_slopes.log" || { cat "$D/modal_slopes.log"; fail "modal-slopes: rank"; }
# the control matrix copied beside the slopes, which name it relative to their folder (MODALCM):
# the folder moved, teach below still finds it
"$(dirname "$B")/tests/fitsdiff" "$S/cm_modes.fits" "$D/unproj/cm_modes.fits" || fail "modal-slopes: no copy of the CM"
head -c 8640 "$D/unproj/modal_000.fits" | grep -aq "MODALCM = 'cm_modes.fits'" || fail "modal-slopes: MODALCM"
mv "$D/unproj" "$D/unproj_moved" && mkdir -p "$D/unproj" && mv "$D/unproj_moved" "$D/unproj/moved"
grep -Eq "cannot have made: [0-9.]+e-(0[7-9]|1[0-9]) of their rms" "$D/modal_slopes.log" \
    || { cat "$D/modal_slopes.log"; fail "modal-slopes: the coefficients should be CM's own"; }
rel=$("$(dirname "$B")/tests/fitsdiff" --rms "$S/slopes_valid_000.fits" "$D/unproj/moved/modal_000.fits")
awk -v r="$rel" 'BEGIN { exit !(r > 0 && r < 0.15) }' || fail "modal-slopes: the slopes differ by $rel of their rms"
sed "s#$S/slopes_valid_#$D/unproj/moved/modal_#" "$D/timing_valid.txt" > "$D/timing_unproj.txt"
unproj=$(linear unproj "$D/timing_unproj.txt" --actuators "$S/actuators.fits" --valid "$S/valid.fits" \
    --pupil "$S/pupil.fits" --teach-loops 4 --teach-max-loops 4 --teach-set dm_coupling=0)
grep -q "chose the .* map" "$D/speckles_unproj.log" || { cat "$D/speckles_unproj.log"; fail "modal-slopes: no taught map"; }
grep -q "modal-slopes' projection (MODALCM): the loops' slopes learned on the same projection, rank 216 of 224" \
    "$D/speckles_unproj.log" || { cat "$D/speckles_unproj.log"; fail "modal-slopes: teach should project its loops' slopes"; }
echo "cli_modal: modal-slopes: the slopes within $rel of their rms; NCP error $unproj nm (native $native nm)" >&2
awk -v a="$unproj" -v b="$native" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "modal-slopes: $unproj nm against $native nm"
# --recon vk on those slopes: their effective noise (white and aliasing) from their curl's power
# (the slopes outside the modes, from which vk estimates it on slopes of its own, are gone),
# not a map without noise (297 nm before)
unvk=$(linear unvk "$D/timing_unproj.txt" --actuators "$S/actuators.fits" --valid "$S/valid.fits" --recon vk)
grep -q "slope noise [0-9.e-]* rad rms (the slopes' curl power: modal-slopes' projection" "$D/speckles_unvk.log" \
    || { cat "$D/speckles_unvk.log"; fail "modal-slopes + vk: the noise should come from the curl"; }
echo "cli_modal: modal-slopes + vk: NCP error $unvk nm (vk on the valid slopes: $valid nm)" >&2
awk -v a="$unvk" -v b="$valid" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "modal-slopes + vk: $unvk nm against $valid nm"
# refused: a control matrix of another shape (control.fits maps 224 slopes to 217 actuators),
# and the inputs' own folder as the output; nothing written
mkdir -p "$D/unproj2"
"$B" modal-slopes "$S/modal_000.fits" --cm "$S/control.fits" -o "$D/unproj2" > "$D/ms_bad.log" 2>&1 && fail "modal-slopes: wrong CM"
grep -q "modal_000.fits: 216 coefficients per WFS frame; .*control.fits maps 224 slopes to 217" "$D/ms_bad.log" \
    || { cat "$D/ms_bad.log"; fail "modal-slopes: the message"; }
[ -z "$(ls "$D/unproj2")" ] || fail "modal-slopes left files after refusing"
"$B" modal-slopes "$S/modal_000.fits" --cm "$S/cm_modes.fits" --imat "$S/rm_modes.fits" -o "$D/unproj2" > "$D/ms_bad.log" 2>&1 \
    && fail "modal-slopes: --cm and --imat"
grep -q "takes --cm or --imat, not both" "$D/ms_bad.log" || { cat "$D/ms_bad.log"; fail "modal-slopes: --cm and --imat message"; }
[ -z "$(ls "$D/unproj2")" ] || fail "modal-slopes left files after refusing"
# through the modal response matrix (--imat): its pseudo-inverse is the control matrix taken,
# written beside the slopes and named by them; s' = RM c. The export's coefficients come
# through a von Karman MAP, which shrinks the modes RM's pseudo-inverse does not: the slopes
# are then further from the true ones than through the CM's pseudo-inverse, and modal-slopes
# says so from the coefficients' white noise per mode (docs/telemetry.md;
# the exact case, a least-squares CM, is python/tests/test_sim.py's test_modal_slopes)
mkdir -p "$D/viaim"
"$B" modal-slopes "$S"/modal_0*.fits --imat "$S/rm_modes.fits" -o "$D/viaim" > "$D/ms_imat.log" 2>&1 \
    || { cat "$D/ms_imat.log"; fail "modal-slopes --imat"; }
grep -q "216 coefficients -> 224 slopes through the response matrix .* (rank 216," "$D/ms_imat.log" \
    || { cat "$D/ms_imat.log"; fail "modal-slopes --imat: rank"; }
head -c 8640 "$D/viaim/modal_000.fits" | grep -aq "MODALCM = 'pinv_rm_modes.fits'" || fail "modal-slopes --imat: MODALCM"
grep -q "warning: the coefficients' white noise is not what a least-squares control matrix of .*rm_modes.fits gives" \
    "$D/ms_imat.log" || { cat "$D/ms_imat.log"; fail "modal-slopes --imat: the MAP's coefficients should be flagged"; }
[ -f "$D/viaim/pinv_rm_modes.fits" ] || fail "modal-slopes --imat: no pinv_rm_modes.fits"
relim=$("$(dirname "$B")/tests/fitsdiff" --rms "$S/slopes_valid_000.fits" "$D/viaim/modal_000.fits")
echo "cli_modal: modal-slopes --imat: the slopes within $relim of their rms (through the CM: $rel)" >&2
awk -v r="$relim" -v c="$rel" 'BEGIN { exit !(r > c && r < 1) }' || fail "modal-slopes --imat: the slopes differ by $relim of their rms"
# the slopes carry the check's verdict (MODALLSQ, MODALRGW), and speckles repeats the warning
head -c 8640 "$D/viaim/modal_000.fits" | grep -aq "MODALRGW=  *1 " || fail "modal-slopes --imat: MODALRGW"
sed "s#$S/slopes_valid_#$D/viaim/modal_#" "$D/timing_valid.txt" > "$D/timing_viaim.txt"
"$B" speckles "$D/timing_viaim.txt" --science "$D/science.fits" --actuators "$S/actuators.fits" --valid "$S/valid.fits" \
    --recon vk -o "$D/sp_viaim.fits" 2> "$D/speckles_viaim.log" || { cat "$D/speckles_viaim.log"; fail "speckles on --imat's slopes"; }
grep -q "warning: these slopes came through modal-slopes --imat from coefficients whose white noise" "$D/speckles_viaim.log" \
    || { cat "$D/speckles_viaim.log"; fail "speckles: no warning on --imat's slopes of a regularizing CM"; }
! grep -q "warning: these slopes came through modal-slopes --imat" "$D/speckles_unvk.log" || fail "speckles: warned on --cm's slopes"
"$B" modal-slopes "$S/modal_000.fits" --cm "$S/cm_modes.fits" -o "$S" > "$D/ms_bad.log" 2>&1 && fail "modal-slopes into the inputs' folder"
grep -q "is in the output folder" "$D/ms_bad.log" || { cat "$D/ms_bad.log"; fail "modal-slopes: same folder"; }
# the control matrix in the output folder, where its copy would be written over it: refused, as it was
mkdir -p "$D/ms_cm" && cp "$S/cm_modes.fits" "$D/ms_cm/"
"$B" modal-slopes "$S/modal_000.fits" --cm "$D/ms_cm/cm_modes.fits" -o "$D/ms_cm" > "$D/ms_cm.log" 2>&1 \
    && fail "modal-slopes with its control matrix in the output folder"
grep -q "the control matrix .*ms_cm/cm_modes.fits is in the output folder" "$D/ms_cm.log" && cmp -s "$S/cm_modes.fits" \
    "$D/ms_cm/cm_modes.fits" && [ ! -e "$D/ms_cm/modal_000.fits" ] \
    || { cat "$D/ms_cm.log"; fail "modal-slopes: the control matrix in the output folder, kept as it was"; }
noflip=$(linear noflip "$D/timing_modal.txt" --basis "$S/dm_modes.fits" $(echo "$reg" | sed 's/--dm-flip//') \
    --coef-scale 2e-6)
echo "cli_modal: NCP error native $native nm, modal $modal nm, control $control nm; modal unmirrored $noflip nm" >&2
grep -q "216 basis functions.*from the DM grid" "$D/speckles_modal.log" || { cat "$D/speckles_modal.log"; fail "modal summary"; }
# modal coefficients as given: the summary points to modal-slopes (no such note with a control matrix)
grep -q "note: no map is taught for a linear model.*modal-slopes" "$D/speckles_modal.log" || fail "modal: the note"
! grep -q "note: no map is taught" "$D/speckles_control.log" || fail "control: a note for modal coefficients"
for e in "$modal" "$control"; do
    awk -v a="$e" -v b="$native" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "NCP error $e nm against $native nm native"
done
awk -v a="$noflip" -v b="$native" 'BEGIN { exit !(a > 1.5 * b) }' || fail "unmirrored registration: $noflip nm"
# export_truth=1: the true residual on the actuators (truewf_NNN.fits, the slopes' frames) as the
# telemetry of the actuators' influence functions gives the ideal speckles' NCP error: nothing
# between the actuators and the estimate loses what the ideal speckles have.
sed "s#/slopes_#/truewf_#" "$D/timing.txt" > "$D/timing_truth.txt"
truth=$(linear truth "$D/timing_truth.txt" --basis "$S/influence.fits" --coef-scale 1)
"$B" estimate "$D/science.fits" "$S/speckles_ideal.fits" -o "$D/halo_ideal.fits" > /dev/null 2>&1 || fail "estimate (ideal)"
"$B" pupil "$D/halo_ideal.fits" -o "$D/pupil_ideal.fits" --truth "$S/truth.fits" > "$D/pupil_ideal.log" || fail "pupil (ideal)"
ideal=$(ncp_error "$D/pupil_ideal.log")
echo "cli_modal: the true residual on the actuators $truth nm, the ideal speckles $ideal nm" >&2
awk -v a="$truth" -v b="$ideal" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "truth on the actuators: $truth nm against $ideal nm"
# the report draws the registration from the keys speckles recorded
mkdir -p "$D/rep"
cp "$D/sci_modal.fits" "$D/rep/science.fits"
cp "$D/sp_modal.fits" "$D/rep/speckles.fits"
"$B" report "$D/rep" -o "$D/rep/out" > "$D/report.log" 2>&1 || { cat "$D/report.log"; fail "report"; }
if grep -q "registration.png" "$D/report.log"; then
    [ -s "$D/rep/out/registration.png" ] || fail "report: no registration.png"
else
    grep -q "0 figures\|PLplot" "$D/report.log" || { cat "$D/report.log"; fail "report: no registration figure"; }
fi
# stream runs the same model frame by frame
# shellcheck disable=SC2086
"$B" stream --timing "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" $reg --coef-scale 2e-6 \
    -o "$D/halo_stream.fits" > "$D/stream.log" 2>&1 || { cat "$D/stream.log"; fail "stream --basis"; }
"$B" pupil "$D/halo_stream.fits" -o "$D/pupil_stream.fits" --truth "$S/truth.fits" > "$D/pupil_stream.log" || fail "pupil"
streamed=$(ncp_error "$D/pupil_stream.log")
echo "cli_modal: stream --basis: NCP error $streamed nm" >&2
awk -v a="$streamed" -v b="$modal" 'BEGIN { exit !(a > 0 && a < 1.05 * b && a > 0.95 * b) }' || fail "stream: $streamed nm"
# live takes the modal stream as it takes slopes: replay publishes the modal files
mkdir -p "$D/shm"
# shellcheck disable=SC2086
"$B" live --shm-dir "$D/shm" --wfs w --camera c --geom "$D/science.fits" --basis "$S/dm_modes.fits" $reg \
    --coef-scale 2e-6 --batch 8 --max-wait 60 --idle-exit 0.5 -o "$D/halo_live.fits" > "$D/live.log" 2>&1 &
live_pid=$!
"$B" replay --shm-dir "$D/shm" --wfs-name w --camera-name c --timing "$D/timing_modal.txt" --science "$D/science.fits" \
    --wait-reader 30 --depth 256 --remove --wfs-rate 1000 > "$D/replay.log" 2>&1 || { cat "$D/replay.log"; fail "replay"; }
wait "$live_pid" || { cat "$D/live.log"; fail "live --basis"; }
grep -q "halo_live.fits: 180 camera frames used" "$D/live.log" || { cat "$D/live.log"; fail "live: frames"; }
"$B" pupil "$D/halo_live.fits" -o "$D/pupil_live.fits" --truth "$S/truth.fits" > "$D/pupil_live.log" || fail "pupil"
lived=$(ncp_error "$D/pupil_live.log")
echo "cli_modal: live --basis: NCP error $lived nm" >&2
awk -v a="$lived" -v b="$streamed" 'BEGIN { exit !(a > 0 && a < 1.05 * b && a > 0.95 * b) }' || fail "live: $lived nm"
# --imat with fewer independent columns than basis functions: the modal response matrix with its
# last 16 columns (of 216) made copies of columns 184..199 has rank 200; speckles runs on it and
# its summary notes the rank, the 200 combinations the telemetry senses and the 16 never
# reconstructed (swfs_pipeline_info.imat_rank); the matrix itself, rank 216, gets no such note
/usr/bin/python3 "$(dirname "$0")/tools/fitshdr.py" "$S/rm_modes.fits" "$D/rm_rank200.fits" --copy-columns 184 200 16
for im in "$S/rm_modes.fits" "$D/rm_rank200.fits"; do
    n=$(basename "$im" .fits)
    # shellcheck disable=SC2086
    "$B" speckles "$D/timing_valid.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" $reg --coef-scale 2e-6 \
        --imat "$im" --mean-loop none -o "$D/sp_$n.fits" 2> "$D/speckles_$n.log" \
        || { cat "$D/speckles_$n.log"; fail "speckles --imat $n"; }
    grep -q "216 basis functions .*interaction matrix, MAP reconstructor" "$D/speckles_$n.log" \
        || { cat "$D/speckles_$n.log"; fail "speckles --imat $n: the model's summary"; }
done
grep -qF "speckles: note: the interaction matrix $D/rm_rank200.fits has rank 200 of its 216 basis functions: the telemetry \
senses 200 combinations of their coefficients, and the other 16 are never reconstructed (a column that repeats another" \
    "$D/speckles_rm_rank200.log" || { cat "$D/speckles_rm_rank200.log"; fail "--imat of rank 200: no rank note"; }
! grep -q "note: the interaction matrix" "$D/speckles_rm_modes.log" || fail "--imat of full rank: a rank note"
# Refused, naming file and value, no output left:
o="$D/bad.fits"
expect_error "the basis is 63 x 63 x 216 but the pupil grid is PUPN = 66" \
    "$B" speckles "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" -o "$o"
expect_error "control.fits: the control matrix .* expected NAXIS1 = 216" \
    "$B" speckles "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/influence.fits" --control "$S/control.fits" -o "$o"
# shellcheck disable=SC2086
expect_error "waves at 3.8 um; expected 1e-05..4 waves.*scale (1)" \
    "$B" speckles "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" $reg -o "$o"
expect_error "illuminated pupil samples more than one grid step beyond the 63 x 63 DM grid" \
    "$B" speckles "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" --dm-pitch 0.05 -o "$o"
expect_error "takes no --actuators" \
    "$B" speckles "$D/timing_modal.txt" --science "$D/science.fits" --basis "$S/dm_modes.fits" --actuators "$S/actuators.fits" -o "$o"
expect_error "slopes_valid_000.fits: 224 slopes per frame is not 2 nsub^2.*valid-subaperture map" \
    "$B" speckles "$D/timing_valid.txt" --science "$D/science.fits" --actuators "$S/actuators.fits" -o "$o"
expect_error "dm_modes.fits: a valid-subaperture map is a square nsub x nsub image" \
    "$B" speckles "$D/timing_valid.txt" --science "$D/science.fits" --actuators "$S/actuators.fits" \
    --valid "$S/dm_modes.fits" -o "$o"
# a control matrix with an element of 1e300 (its products would overflow), an interaction matrix
# with a NaN: named, file and element
/usr/bin/python3 "$(dirname "$0")/tools/fitshdr.py" "$S/recon_ao.fits" "$D/cbig.fits" --fill 1e300 1
/usr/bin/python3 "$(dirname "$0")/tools/fitshdr.py" "$S/recon_ao.fits" "$D/inan.fits" --fill nan 50
expect_error "cbig.fits: element (1, 1) of the control matrix is 1e+300; expected finite and below 1e30" \
    "$B" speckles "$D/timing.txt" --science "$D/science.fits" --basis "$S/influence.fits" --control "$D/cbig.fits" -o "$o"
expect_error "inan.fits: element (1, 1) of the matrix is not finite (NaN or infinite)" \
    "$B" speckles "$D/timing.txt" --science "$D/science.fits" --basis "$S/influence.fits" --imat "$D/inan.fits" -o "$o"
ls "$D"/bad.fits* > /dev/null 2>&1 && fail "an output was left after a refusal"
echo "cli_modal: ok"
