# The real-data path end to end on a small time-series simulation:
#   simulate mode=timeseries -> reduce -> sync -> speckles -> estimate -> pupil
# asserting the recovered frame ratio (+-0.03) and handshake lag (+-1 WFS frame), the use of
# a cube that crosses from one telemetry file into the next (its exposures in either file, the
# files found contiguous on the data; only the exposure across the boundary left out), the
# frame-for-frame match of
# the speckle and science cubes, the NCP error of the recovered wavefront, and clear
# errors for bad input.
# usage: bash cli_telemetry.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"

# 3 cubes x 60 frames at <t_sci/t_wfs> = 6.48, lag 3; telemetry files of 1000 WFS frames,
# so cube 1 (WFS frames ~839..1228) straddles slopes_000/slopes_001.
"$B" simulate mode=timeseries --quiet -o "$D/sim" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=60 \
    cube_gap=150 layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 wfs_file_frames=1000 seed=1 > "$D/sim.log" \
    || fail "simulate"
for f in slopes_000.fits slopes_001.fits actuators.fits recon_ao.fits handshake.log raw_000.fits raw_002.fits \
         dark.fits flat.fits speckles_ideal.fits truth.fits; do
    [ -f "$D/sim/$f" ] || fail "simulate did not write $f"
done

# The paper's path: registered science frames (reduce re-centres every frame on its peak)
# and speckles with the exposure-mean tip-tilt removed (speckles' default --tiptilt
# exposure: the motion within an exposure stays, as blur, in both).
"$B" reduce "$D"/sim/raw_000.fits "$D"/sim/raw_001.fits "$D"/sim/raw_002.fits --dark "$D/sim/dark.fits" \
    --flat "$D/sim/flat.fits" -o "$D/science.fits" 2> "$D/reduce.log" || fail "reduce"
# The simulated read noise is 19 counts; the photon part is left to estimate (Phi_I/GAIN) and
# the bilinear registration scales the variance by ~4/9 (NOISEFAC).
rn=$(sed -n 's/.*background noise \([0-9.]*\) counts rms (\([0-9.]*\) after.*/\1 \2/p' "$D/reduce.log")
awk -v r="$rn" 'BEGIN { split(r, a, " "); exit !(a[1] > 18 && a[1] < 20.5 && a[2] > 0.6 * a[1] && a[2] < 0.75 * a[1]) }' \
    || fail "reduce noise '$rn' (raw, registered): expected ~19 and ~2/3 of it"
"$B" sync "$D/science.fits" "$D/sim/handshake.log" -o "$D/timing.txt" --ratio-min 5 --ratio-max 8 > "$D/sync.log" \
    || fail "sync"
cat "$D/sync.log"
ratio=$(awk '$1 == "ratio" {print $2}' "$D/timing.txt")
lag=$(awk '$1 == "lag" {print $2}' "$D/timing.txt")
awk -v r="$ratio" 'BEGIN { d = r - 6.48; if (d < 0) d = -d; exit !(d <= 0.03) }' || fail "ratio $ratio not within 0.03 of 6.48"
awk -v l="$lag" 'BEGIN { d = l - 3; if (d < 0) d = -d; exit !(d <= 1) }' || fail "lag $lag not within 1 of 3"
[ "$(awk '$1 == "cube" && $8 == "straddles" && $5 == 1' "$D/timing.txt" | wc -l)" -eq 1 ] \
    || fail "expected one straddling exposure"
[ "$(awk '$1 == "cube" && $8 == "ok"' "$D/timing.txt" | wc -l)" -eq 4 ] || fail "expected four usable rows"
[ "$(awk '$1 == "cube" && $3 == "raw_001.fits" && $8 == "ok" && $6 ~ /slopes_001.fits$/' "$D/timing.txt" | wc -l)" -eq 1 ] \
    || fail "expected raw_001.fits to continue in slopes_001.fits"
grep -q "^# raw_001.fits frames .* continue in the next or previous telemetry file" "$D/timing.txt" \
    || fail "the timing table does not say which part continues"
grep -q "179 of 180 exposures usable" "$D/sync.log" || fail "sync's count of usable exposures"
# A handshake log elsewhere naming the slopes files by absolute path: used as they are, not
# joined to the log's folder; the same timing.
mkdir -p "$D/logs"
sim_abs=$(cd "$D/sim" && pwd)
awk -v d="$sim_abs" '/^#/ || NF < 3 { print; next } { $2 = d "/" $2; print }' "$D/sim/handshake.log" > "$D/logs/abs.log"
grep -q "^[^#].* $sim_abs/slopes_000.fits" "$D/logs/abs.log" || fail "the absolute handshake log"
"$B" sync "$D/science.fits" "$D/logs/abs.log" -o "$D/timing_abs.txt" --ratio-min 5 --ratio-max 8 > "$D/sync_abs.log" \
    || { cat "$D/sync_abs.log"; fail "sync with absolute slopes paths in the handshake log"; }
[ "$(awk '$1 == "ratio" || $1 == "lag"' "$D/timing_abs.txt")" = "$(awk '$1 == "ratio" || $1 == "lag"' "$D/timing.txt")" ] \
    || fail "absolute handshake paths: another timing"

"$B" speckles "$D/timing.txt" --science "$D/science.fits" --actuators "$D/sim/actuators.fits" -o "$D/speckles.fits" \
    --recon vk --match "$D/science.fits" "$D/sci_m.fits" 2> "$D/speckles.log" || { cat "$D/speckles.log"; fail "speckles"; }
grep -q "179 frames from 4 of 5 timing-table rows" "$D/speckles.log" || { cat "$D/speckles.log"; fail "speckles frame count"; }
"$B" estimate "$D/sci_m.fits" "$D/speckles.fits" -o "$D/halo.fits" > "$D/estimate.log" || fail "estimate on the matched cubes"
"$B" pupil "$D/halo.fits" -o "$D/pupil.fits" --source halo --truth "$D/sim/truth.fits" > "$D/pupil.log" || fail "pupil"
cat "$D/pupil.log"
# NCP error (piston, tip, tilt removed) against the 90.7 nm injected without tip/tilt:
# measured 35.6 nm with speckles --recon vk (the default before --recon teach) (41.8 nm before the cube crossing into
# slopes_001 was used; seed 1; reduce's RDNOISE is the registered frames' read noise). Seed 5
# puts a bad pixel by the core, whose 3x3-median error inflates the out-of-band noise
# estimate (docs/telemetry.md, open problems).
err=$(awk '/versus truth/ { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$D/pupil.log")
awk -v e="$err" 'BEGIN { exit !(e > 0 && e < 50) }' || fail "NCP error $err nm, expected < 50 nm"
# --tiptilt frame, the paper's Sec. 4.4: every WFS frame's own mean-slope tilt removed from
# the speckles, and the --match copies re-centred on the exposure-mean tilt the slopes measure
# instead of the image peak (which follows the Z-tilt and the NCP's own tilt). Measured 21.2
# nm against 23.5 nm with the exposure-mean treatment (seed 1); before the re-centring the
# per-frame path broke down (310 nm).
"$B" speckles "$D/timing.txt" --science "$D/science.fits" --actuators "$D/sim/actuators.fits" -o "$D/speckles_f.fits" \
    --recon vk --tiptilt frame --match "$D/science.fits" "$D/sci_f.fits" 2> "$D/speckles_f.log" \
    || { cat "$D/speckles_f.log"; fail "speckles --tiptilt frame"; }
"$B" estimate "$D/sci_f.fits" "$D/speckles_f.fits" -o "$D/halo_f.fits" > "$D/estimate_f.log" || fail "estimate (frame)"
"$B" pupil "$D/halo_f.fits" -o "$D/pupil_f.fits" --truth "$D/sim/truth.fits" > "$D/pupil_f.log" || fail "pupil (frame)"
"$B" pupil "$D/halo.fits" -o "$D/pupil_d.fits" --truth "$D/sim/truth.fits" > "$D/pupil_d.log" || fail "pupil (default)"
errf=$(awk '/versus truth/ { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$D/pupil_f.log")
errd=$(awk '/versus truth/ { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$D/pupil_d.log")
echo "cli_telemetry: --tiptilt frame (re-centred on the slopes' tilt): $errf nm; exposure mean: $errd nm" >&2
awk -v e="$errd" -v f="$errf" 'BEGIN { exit !(f > 0 && f < 1.1 * e) }' || fail "per-frame tip-tilt: $errf nm against $errd nm"

# ---- bad input --------------------------------------------------------------------
# A reconstructor whose length does not match the slopes (here: the 2 x nact actuator table).
expect_error "expects" "$B" speckles "$D/timing.txt" --science "$D/science.fits" --actuators "$D/sim/actuators.fits" \
    -o "$D/x.fits" --recon "$D/sim/actuators.fits"
# A handshake log that does not cover a cube.
grep -v raw_001 "$D/sim/handshake.log" > "$D/sim/short.log"
expect_error "does not cover cube 1" "$B" sync "$D/science.fits" "$D/sim/short.log" -o "$D/x.txt"
# Camera cubes of different frame sizes (the 66 x 66 NCP map as a second "cube").
expect_error "same frame size" "$B" reduce "$D/sim/raw_000.fits" "$D/sim/truth.fits" -o "$D/x.fits"
# A timing table without the ratio line.
grep -v "^ratio" "$D/timing.txt" > "$D/bad_timing.txt"
expect_error "ratio" "$B" speckles "$D/bad_timing.txt" --science "$D/science.fits" --actuators "$D/sim/actuators.fits" \
    -o "$D/x.fits"
echo "cli_telemetry: ok (ratio $ratio, lag $lag, NCP error $err nm; per-frame tip-tilt $errf nm)"
