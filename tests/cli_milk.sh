# milk/cacao logs and timing from time stamps, against the handshake path on the same data:
#   simulate mode=timeseries milk=1 (slopes and raw camera frames also as milk logs: several
#   files per stream, 3 us stamp jitter, camera clock drift 1e-4 and offset 2.5 ms, 5 WFS and
#   3 camera frames dropped, EXPTIME), one WFS file tile-compressed;
#   native: reduce raw_* -> sync handshake.log -> speckles --write-recon -> stream --timing;
#   milk:   reduce milk/cam/* (STAMPS) -> sync --wfs-log (clock.txt) -> stream --wfs-log --clock.
# Asserts the drift (within 2e-5 of 1e-4) and the offset (within 0.3 ms of 2.5 ms), the drops
# counted exactly, the NCP error of the milk path within 10 % of the native path's, and clear
# errors (file and value named, non-zero exit, no output) for stamps that go back, a table whose
# rows differ from the FITS frames and a WFS log that does not overlap the camera in time.
# usage: bash cli_milk.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
FITSCOPY=$(dirname "$B")/tests/fitscopy
# 6 cubes of 50 frames 2000 WFS frames apart: 27 s of data, so that a drift of 1e-4 moves the
# camera by 2.7 ms (1.4 WFS frames) from the first cube to the last.
"$B" simulate mode=timeseries --quiet -o "$D/sim" pupn=66 pupdx=0.1 screen_n=1024 ncubes=6 cube_frames=50 \
    cube_gap=2000 layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 seed=1 milk=1 milk_file_frames=2000 \
    > "$D/sim.log" || fail "simulate"
truth() { awk -v k="$1" '$1 == k { print $2 }' "$D/sim/milk/truth.txt"; }
nw=$(ls "$D"/sim/milk/wfs/*.fits | wc -l)
nc=$(ls "$D"/sim/milk/cam/*.fits | wc -l)
[ "$nw" -ge 3 ] && [ "$nc" -ge 6 ] || fail "expected several files per stream, got $nw WFS and $nc camera files"
# One WFS file tile-compressed, as fpack leaves it (its .txt keeps the name without .fits).
z=$(ls "$D"/sim/milk/wfs/*.fits | sed -n 2p)
"$FITSCOPY" "$z" "$z.fz[compress G]" lossless && rm "$z" || fail "fitscopy"

# ---- native: the handshake path -----------------------------------------------------------
"$B" reduce "$D"/sim/raw_*.fits --dark "$D/sim/dark.fits" --flat "$D/sim/flat.fits" -o "$D/science.fits" \
    2> "$D/reduce.log" || fail "reduce"
"$B" sync "$D/science.fits" "$D/sim/handshake.log" -o "$D/timing.txt" --ratio-min 5 --ratio-max 8 > "$D/sync.log" \
    || { cat "$D/sync.log"; fail "sync"; }
"$B" speckles "$D/timing.txt" --science "$D/science.fits" --actuators "$D/sim/actuators.fits" -o "$D/speckles.fits" --recon vk \
    --write-recon "$D/recon.fits" 2> "$D/speckles.log" || { cat "$D/speckles.log"; fail "speckles"; }
stream_pupil() { # stream_pupil <name> <stream args...>: prints the NCP error
    local n=$1; shift
    "$B" stream --recon "$D/recon.fits" --actuators "$D/sim/actuators.fits" -o "$D/halo_$n.fits" "$@" \
        > "$D/stream_$n.log" 2>&1 || { cat "$D/stream_$n.log"; fail "stream ($n)"; }
    "$B" pupil "$D/halo_$n.fits" -o "$D/pupil_$n.fits" --truth "$D/sim/truth.fits" > "$D/pupil_$n.log" \
        || fail "pupil ($n)"
    ncp_error "$D/pupil_$n.log"
}
en=$(stream_pupil native --timing "$D/timing.txt" --science "$D/science.fits")

# ---- milk: time stamps ----------------------------------------------------------------------
"$B" reduce "$D"/sim/milk/cam/*.fits --dark "$D/sim/dark.fits" --flat "$D/sim/flat.fits" -o "$D/sci_milk.fits" \
    2> "$D/reduce_milk.log" || { cat "$D/reduce_milk.log"; fail "reduce (milk)"; }
grep -q "STAMPS: $(truth cam_dropped) camera frames dropped" "$D/reduce_milk.log" \
    || { cat "$D/reduce_milk.log"; fail "reduce: camera drops"; }
"$B" sync --wfs-log "$D/sim/milk/wfs" "$D/sci_milk.fits" -o "$D/clock.txt" > "$D/sync_milk.log" \
    || { cat "$D/sync_milk.log"; fail "sync --wfs-log"; }
cat "$D/sync_milk.log"
grep -q "($(truth wfs_dropped) dropped)" "$D/sync_milk.log" || fail "sync: WFS drops"
drift=$(awk '$1 == "drift" { print $2 }' "$D/clock.txt")
off=$(awk '$1 == "offset" { print $2 }' "$D/clock.txt")
# Both clocks' epoch is a whole second: the simulator's (1.7e9) when the camera starts within it.
awk -v e="$(awk '$1 == "epoch" { print $2 }' "$D/clock.txt")" -v t="$(truth epoch)" 'BEGIN { exit !(e == t) }' \
    || fail "clock epoch differs from the simulated one"
awk -v d="$drift" -v t="$(truth drift)" 'BEGIN { x = d - t; if (x < 0) x = -x; exit !(x <= 2e-5) }' \
    || fail "drift $drift not within 2e-5 of $(truth drift)"
awk -v o="$off" -v t="$(truth offset)" 'BEGIN { x = o - t; if (x < 0) x = -x; exit !(x <= 3e-4) }' \
    || fail "offset $off s not within 0.3 ms of $(truth offset) s"
em=$(stream_pupil milk --wfs-log "$D/sim/milk/wfs" --clock "$D/clock.txt" --science "$D/sci_milk.fits")
grep -q "dropped $(truth cam_dropped) camera and $(truth wfs_dropped) WFS frames" "$D/stream_milk.log" \
    || { cat "$D/stream_milk.log"; fail "stream: drops"; }
echo "clock: drift $drift (true $(truth drift)), offset $off s (true $(truth offset)); NCP error: native $en nm, milk $em nm"
awk -v a="$en" -v b="$em" 'BEGIN { exit !(a > 0 && a < 35 && b > 0 && b <= 1.1 * a) }' \
    || fail "milk path NCP error $em nm against $en nm for the handshake path"

# ---- bad input ----------------------------------------------------------------------------
bad_copy() { rm -rf "$D/$1"; cp -r "$D/sim/milk/wfs" "$D/$1"; }
first_txt() { ls "$D/$1"/*.txt | head -1; }
# Stamps that go back: line 10's acquisition time set to line 5's.
bad_copy back
t=$(first_txt back)
awk 'NR == 5 { s = $5 } NR == 10 { $5 = s } { print }' "$t" > "$t.new" && mv "$t.new" "$t"
expect_error "$(basename "$t"):10: time stamp .* goes back" "$B" sync --wfs-log "$D/back" "$D/sci_milk.fits" \
    -o "$D/x_clock.txt"
[ ! -e "$D/x_clock.txt" ] || fail "sync left a clock file after refusing"
# A table with one row less than its FITS file's frames.
bad_copy rows
t=$(first_txt rows)
sed -i '$d' "$t"
expect_error "$(basename "$t")" "$B" stream --wfs-log "$D/rows" --clock "$D/clock.txt" --science "$D/sci_milk.fits" \
    --recon "$D/recon.fits" --actuators "$D/sim/actuators.fits" -o "$D/x_halo.fits"
grep -q "holds [0-9]* frames .* but its timestamp table .* lists" "$D/err.log" || { cat "$D/err.log"; fail "row count message"; }
[ ! -e "$D/x_halo.fits" ] || fail "stream left a product after refusing"
# A WFS log 1000 s later than the camera.
bad_copy late
for t in "$D"/late/*.txt; do
    awk '!/^#/ { sub(/^1700000/, "1700001", $4); sub(/^1700000/, "1700001", $5) } { print }' "$t" > "$t.new" \
        && mv "$t.new" "$t"
done
expect_error "does not overlap in time" "$B" stream --wfs-log "$D/late" --clock "$D/clock.txt" \
    --science "$D/sci_milk.fits" --recon "$D/recon.fits" --actuators "$D/sim/actuators.fits" -o "$D/x_halo.fits"
grep -q "late.*1700001" "$D/err.log" || { cat "$D/err.log"; fail "no-overlap message lacks the log and its stamps"; }
[ ! -e "$D/x_halo.fits" ] || fail "stream left a product after refusing"
expect_error "lies inside the WFS data" "$B" sync --wfs-log "$D/late" "$D/sci_milk.fits" -o "$D/x_clock.txt"
[ ! -e "$D/x_clock.txt" ] || fail "sync left a clock file after refusing"
# reduce: camera logs mixed with a raw cube that has no table; a camera table one row short.
c=$(ls "$D"/sim/milk/cam/*.fits | head -1)
expect_error "has none" "$B" reduce "$c" "$D/sim/raw_001.fits" -o "$D/x_sci.fits"
rm -rf "$D/camrows" && mkdir "$D/camrows" && cp "$c" "${c%.fits}.txt" "$D/camrows/"
sed -i '$d' "$D"/camrows/*.txt
expect_error "holds [0-9]* frames but its timestamp table .*camrows.* lists" "$B" reduce "$D"/camrows/*.fits -o "$D/x_sci.fits"
[ ! -e "$D/x_sci.fits" ] || fail "reduce left an output after refusing"
echo "cli_milk: ok"
