# The science camera's orientation: a camera mirrored in x, one transposed, and one both
# transposed and mirrored in x and y, simulated (simulate camera_flip_x / camera_swap /
# camera_flip_y) and run through reduce -> sync -> speckles -> estimate -> pupil with default
# options. sync must find the pairing, speckles must turn the matched science frames into
# the model's orientation (CAMORIEN), and the NCP must come out as well as with the camera
# as the model (measured 23.0 nm; 21.5 / 22.5 / 22.9 nm turned; ignoring the mirror gave
# 77.5 nm). estimate refuses the camera's own frames with speckles made for a turned camera,
# and stream refuses a copy already turned.
# usage: bash cli_orient.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
SPK_RECON=(--recon vk) # the von Karman map: this test is not about the reconstructor
run() { # run <name> <expected pairing: swap sx sy> [simulate keys...]: prints the NCP error
    local n=$1 want=$2; shift 2
    local d="$D/$n"
    "$B" simulate mode=timeseries --quiet -o "$d/sim" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=60 \
        cube_gap=150 layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 nfx=54 nfy=54 seed=1 "$@" > "$D/$n.sim.log" \
        || fail "$n: simulate"
    reduce_sync "$d" --ratio-min 5 --ratio-max 8
    local got
    got=$(awk '$1 == "pairing" {print $2, $3, $4}' "$d/timing.txt")
    [ "$got" = "$want" ] || fail "$n: sync's pairing '$got', expected '$want'"
    speckles_pupil "$d"
}
e0=$(run plain "0 1 1")
e1=$(run flipx "0 -1 1" camera_flip_x=1)
e2=$(run swap "1 1 1" camera_swap=1)
e3=$(run all "1 -1 -1" camera_swap=1 camera_flip_x=1 camera_flip_y=1)
echo "NCP error: camera as the model $e0 nm; mirrored in x $e1 nm; transposed $e2 nm; transposed and mirrored $e3 nm"
for e in "$e1" "$e2" "$e3"; do
    awk -v a="$e0" -v b="$e" 'BEGIN { exit !(a > 0 && a < 35 && b > 0 && b < 1.15 * a) }' \
        || fail "turned camera: NCP error $b nm against $a nm for the camera as the model"
done
grep -q "CAMORIEN" "$D/flipx/sci_m.fits" || fail "the matched science copy records no CAMORIEN"

# A timing table whose pairing ignores the mirror: speckles' orientation check (the science
# frames against |psi|^2) finds the camera's pairing and the products take it, the same NCP as
# the right table's; with --pairing table the table's is kept, with a warning, and the NCP is lost.
wrong_table() { # wrong_table <dir> <speckles options...>: the NCP error with the mirror ignored
    local w=$1 t=$1.timing.txt; shift
    mkdir -p "$w"
    # beside the right table: the telemetry names it gives are taken from its folder
    awk '$1 == "pairing" { $2 = 0; $3 = 1; $4 = 1 } { print }' "$D/flipx/timing.txt" > "$t"
    "$B" speckles "$t" --science "$D/flipx/science.fits" --actuators "$D/flipx/sim/actuators.fits" \
        "${SPK_RECON[@]}" -o "$w/speckles.fits" --match "$D/flipx/science.fits" "$w/sci_m.fits" "$@" 2> "$w/speckles.log" \
        || { cat "$w/speckles.log"; fail "$w: speckles"; }
    "$B" estimate "$w/sci_m.fits" "$w/speckles.fits" -o "$w/halo.fits" > "$w/estimate.log" 2>&1 || fail "$w: estimate"
    "$B" pupil "$w/halo.fits" -o "$w/pupil.fits" --truth "$D/flipx/sim/truth.fits" > "$w/pupil.log" || fail "$w: pupil"
    ncp_error "$w/pupil.log"
}
ew=$(wrong_table "$D/flipx/wrong")
grep -q "take the speckles' pairing" "$D/flipx/wrong/speckles.log" || { cat "$D/flipx/wrong/speckles.log"; fail "the wrong table's pairing was not replaced"; }
grep -q "CAMORIEN= 'SWAP=0 SX=-1 SY=+1'" "$D/flipx/wrong/sci_m.fits" || fail "the matched copy is not turned by the speckles' pairing"
ek=$(wrong_table "$D/flipx/kept" --pairing table)
grep -q "which was kept" "$D/flipx/kept/speckles.log" || { cat "$D/flipx/kept/speckles.log"; fail "--pairing table: no warning"; }
echo "a table that ignores the mirror: $ew nm (its pairing replaced by the speckles'), $ek nm (kept)"
awk -v a="$e1" -v b="$ew" -v k="$ek" 'BEGIN { d = a - b; if (d < 0) d = -d; exit !(d < 0.02 * a && k > 2 * a) }' \
    || fail "the wrong table: $ew nm with the speckles' pairing, $ek nm kept, against $e1 nm from the right table"

# The camera's own (mirrored) frames with the speckles made for them: refused, no output.
expect_error "speckles --match" "$B" estimate "$D/flipx/science.fits" "$D/flipx/speckles.fits" -o "$D/x.fits"
[ ! -e "$D/x.fits" ] || fail "estimate left an output after refusing"
# stream takes the reduced cube the timing table refers to, not a turned copy.
"$B" speckles "$D/flipx/timing.txt" --science "$D/flipx/science.fits" --actuators "$D/flipx/sim/actuators.fits" \
    --recon vk -o "$D/flipx/sp2.fits" --write-recon "$D/flipx/recon.fits" 2> /dev/null || fail "speckles --write-recon"
expect_error "already turned" "$B" stream --timing "$D/flipx/timing.txt" --science "$D/flipx/sci_m.fits" \
    --recon "$D/flipx/recon.fits" --actuators "$D/flipx/sim/actuators.fits" -o "$D/x.fits"
# stream on the camera's frames turns them as it reads them: the same halo as speckles + estimate.
"$B" stream --timing "$D/flipx/timing.txt" --science "$D/flipx/science.fits" --recon "$D/flipx/recon.fits" \
    --actuators "$D/flipx/sim/actuators.fits" -o "$D/flipx/halo_stream.fits" --static none > "$D/stream.log" 2>&1 \
    || { cat "$D/stream.log"; fail "stream on a mirrored camera"; }
"$B" pupil "$D/flipx/halo_stream.fits" -o "$D/flipx/pupil_stream.fits" --truth "$D/flipx/sim/truth.fits" \
    > "$D/pupil_stream.log" || fail "pupil (stream)"
es=$(ncp_error "$D/pupil_stream.log")
echo "stream on the mirrored camera: $es nm"
awk -v a="$e1" -v b="$es" 'BEGIN { d = a - b; if (d < 0) d = -d; exit !(d < 0.1 * a) }' \
    || fail "stream on the mirrored camera: $es nm against $e1 nm from speckles + estimate"
echo "cli_orient: ok"
