# docs/telemetry.md's recipe for a reconstructor learned from simulated closed loops, run as
# written there (the training loops on the observation's actuators.fits, valid.fits and
# pupil.fits, their first layer at the wind `specklewfs wind` finds in the observation's
# slopes: 14.64 m/s toward 0 deg for its 15 m/s layer) on a small system (my.conf: the
# 12 x 12 Shack-Hartmann of 217 actuators on a 66-sample pupil, 3 cubes of 60 camera frames):
# six simulated loops -> learn -> speckles --recon on an observation of its own seed (15/22
# m/s), then estimate and pupil --truth. The learned map must come out no worse than the
# default reconstructor on that observation (measured 23.3 nm against 23.3: on so small a data
# set the two are alike through the whole path; the gain is in docs/telemetry.md's matrix),
# and learn must print the held-out check for every folder (measured 0.65-0.67, training
# 0.55). The same map given to the linear model as a control matrix over the influence
# functions gives the same NCP error within 10 % (measured 23.4 nm). A space-time map of the
# same loops (learn --lags) goes through speckles, which prints its two checks against the
# observation (the winds, the slopes' correlation at the lags).
# Then teach (the same rule in one command), described and from the observation's files, and
# its refusals; cli_teach.sh runs speckles' default (teach inside speckles) and its reuse.
# usage: bash cli_learn.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_learn.sh"
learn_setup "$@"
# the recipe, with `specklewfs` the binary under test
recipe=$(sed -n '/<!-- learn-recipe:start -->/,/<!-- learn-recipe:end -->/p' \
    "$(dirname "$0")/../docs/telemetry.md" | sed '1,2d;$d' | sed '$d')
[ -n "$recipe" ] || fail "no learn recipe in docs/telemetry.md"
specklewfs() { "$B" "$@"; }
eval "$recipe" > recipe.log 2>&1 || { cat recipe.log; fail "the recipe failed"; }
[ -s learned.fits ] && [ -s speckles.fits ] && [ -s science_m.fits ] || fail "the recipe left no map or speckles"
[ "$(ls -d train/*/ | wc -l)" = 6 ] || fail "the recipe should simulate six loops"
grep -q "learn: held out, all 6:" recipe.log || { cat recipe.log; fail "learn printed no held-out check"; }
[ "$(grep -c '^  train/' recipe.log)" = 6 ] || { cat recipe.log; fail "learn should list the six folders"; }
# the held-out check over the pupil's annulus (--curve-radius; a truth on the DM's actuators, so
# their positions from actuators.fits): fewer outputs, and a smaller misfit / truth than over
# all of them, whose actuators beyond the pupil carry the truth fit's extrapolation
"$B" learn train/* -o ann.fits --curve-radius 0.325,3.25 --no-mean-miss > learn_ann.log 2>&1 \
    || { cat learn_ann.log; fail "learn --curve-radius (held out)"; }
ra=$(sed -n 's/^learn: held out, all 6: [^(]*(\([0-9.]*\);.* over \([0-9]*\) of \([0-9]*\) outputs$/\1 \2 \3/p' recipe.log)
rp=$(sed -n 's/^learn: held out, all 6: [^(]*(\([0-9.]*\);.* over \([0-9]*\) of \([0-9]*\) outputs (--curve-radius)$/\1 \2 \3/p' learn_ann.log)
set -- $ra $rp
[ $# = 6 ] || { grep "held out, all" recipe.log learn_ann.log; fail "learn: the held-out lines' outputs"; }
awk -v a="$1" -v na="$2" -v p="$4" -v np="$5" -v n="$6" 'BEGIN { exit !(na == n && np < n && np > 0 && p < a) }' \
    || fail "learn: held out over the pupil's annulus $4 ($5 of $6 outputs) against $1 over all ($2)"
echo "cli_learn: held out over the pupil's $5 of $6 actuators: $4 of the truth (all of them: $1)"
# each loop's miss of the mean by the map of the other loops (--mean-miss-heldout): larger than
# by the map of all, which fits its loops' means in-sample
"$B" learn train/* -o mmh.fits --mean-miss-heldout --no-heldout > learn_mmh.log 2>&1 \
    || { cat learn_mmh.log; fail "learn --mean-miss-heldout"; }
m_in=$(sed -n "s/^learn: the map's miss of the residual's time mean: \([0-9.]*\) nm rms per data set.*/\1/p" recipe.log)
m_ho=$(sed -n "s/^learn: the map's miss of the residual's time mean: \([0-9.]*\) nm rms per data set.*/\1/p" learn_mmh.log)
awk -v a="$m_in" -v b="$m_ho" 'BEGIN { exit !(a > 0 && b > a) }' \
    || fail "learn: the held-out miss of the mean $m_ho nm against $m_in nm in-sample"
echo "cli_learn: the loops' miss of the mean per loop: $m_in nm by the map of all, $m_ho nm by the others' map"
"$B" learn train/* -o bad.fits --no-mean-miss --mean-miss-heldout > bad.log 2>&1 && fail "--no-mean-miss --mean-miss-heldout accepted"
grep -q "one or the other" bad.log || { cat bad.log; fail "learn: --no-mean-miss with --mean-miss-heldout's message"; }
"$B" learn train/* -o bad.fits --curve-radius 5,6 > bad.log 2>&1 && fail "an annulus holding no actuator accepted"
grep -q "no output within 5 to 6 m of the centre" bad.log || { cat bad.log; fail "learn: the empty annulus's message"; }
[ -e bad.fits ] && fail "learn left a map after an empty annulus"
"$B" learn "$(ls -d train/*/ | head -1)" -o bad.fits --curve-radius 0.3,3 > bad.log 2>&1 && fail "--curve-radius with one folder accepted"
grep -q -- "--curve-radius is where the checks are measured" bad.log || { cat bad.log; fail "learn: --curve-radius alone"; }
"$B" estimate science_m.fits speckles.fits -o halo_l.fits > /dev/null 2>&1 || fail "estimate (learned)"
"$B" pupil halo_l.fits -o pupil_l.fits --truth obs/truth.fits > pupil_l.log || fail "pupil (learned)"
# the fit's g by ring is printed; --g-radial 0 is the log g of Legendre terms alone (fewer unknowns)
"$B" pupil halo_l.fits -o pupil_l0.fits --truth obs/truth.fits --g-radial 0 > pupil_l0.log || fail "pupil --g-radial 0"
np_of() { sed -n 's/.*focal pixels, \([0-9]*\) parameters.*/\1/p' "$1"; }
[ "$(grep '^  g by ring' pupil_l.log | grep -o ' [0-9]*-[0-9]* [0-9.]*' | wc -l)" -ge 3 ] \
    || { cat pupil_l.log; fail "pupil printed no g by ring"; }
[ -n "$(np_of pupil_l.log)" ] && [ "$(np_of pupil_l0.log)" -lt "$(np_of pupil_l.log)" ] \
    || fail "pupil --g-radial 0: $(np_of pupil_l0.log) parameters, the default $(np_of pupil_l.log)"
echo "cli_learn: pupil of the learned map's halo: $(ncp_error pupil_l.log) nm, with --g-radial 0 $(ncp_error pupil_l0.log) nm"
# the same map as the linear model's control matrix over the actuators' influence functions
# (how a system outside the simulator uses it): the same wavefronts through another
# representation
"$B" speckles timing.txt --science science.fits --basis obs/influence.fits --control learned.fits \
    --match science.fits sci_c.fits -o spk_c.fits 2> speckles_c.log || { cat speckles_c.log; fail "speckles --control"; }
"$B" estimate sci_c.fits spk_c.fits -o halo_c.fits > /dev/null 2>&1 || fail "estimate (control)"
"$B" pupil halo_c.fits -o pupil_c.fits --truth obs/truth.fits > pupil_c.log || fail "pupil (control)"
# the von Karman map on the same observation (--recon vk, the default before --recon teach;
# "default" in the messages below)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --recon vk --match science.fits sci_d.fits \
    -o spk_d.fits 2> speckles_d.log || fail "speckles (vk)"
"$B" estimate sci_d.fits spk_d.fits -o halo_d.fits > /dev/null 2>&1 || fail "estimate (default)"
"$B" pupil halo_d.fits -o pupil_d.fits --truth obs/truth.fits > pupil_d.log || fail "pupil (default)"
# the self-check chooses among the three halos of the same frames: it prints the table and
# uses one of them, no worse than the best by more than 5 %
"$B" pupil halo_d.fits halo_l.fits halo_c.fits -o pupil_ch.fits --truth obs/truth.fits > pupil_ch.log \
    || { cat pupil_ch.log; fail "pupil with three halos"; }
[ "$(grep -c '<- used' pupil_ch.log)" = 1 ] && grep -q "chosen by the self-check among 3 halos" pupil_ch.log \
    || { cat pupil_ch.log; fail "pupil printed no choice"; }
eh=$(ncp_error pupil_ch.log)
el=$(ncp_error pupil_l.log)
ed=$(ncp_error pupil_d.log)
ec=$(ncp_error pupil_c.log)
echo "cli_learn: NCP error with the learned map $el nm (as a control matrix $ec nm), with the von Karman map (vk) $ed nm"
sed -n '/held out in turn/,$p' recipe.log | head -8
awk -v l="$el" -v d="$ed" 'BEGIN { exit !(l > 0 && d > 0 && l < 1.05 * d && d < 40) }' \
    || fail "learned $el nm against the default $ed nm"
echo "cli_learn: the self-check chose $(awk '/<- used/ { print $1 }' pupil_ch.log): $eh nm"
awk -v h="$eh" -v a="$el" -v b="$ed" -v c="$ec" \
    'BEGIN { m = a; if (b < m) m = b; if (c < m) m = c; exit !(h > 0 && h <= 1.05 * m) }' \
    || fail "the halo chosen by the self-check: $eh nm, the three $el $ed $ec nm"
awk -v l="$el" -v c="$ec" 'BEGIN { exit !(c > 0 && c < 1.1 * l && l < 1.1 * c) }' \
    || fail "the learned map as a control matrix $ec nm against $el nm as a reconstructor"
# a prior map (learn --prior): the von Karman map speckles wrote, the loops' map shrunk toward
# it with a ridge that leaves it nothing to move: the von Karman map's NCP error again (0.3 nm);
# a space-time map as the prior is refused (below), no map left
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --recon vk -o spk_d2.fits \
    --write-recon vk.fits 2> /dev/null || fail "speckles --recon vk --write-recon"
"$B" learn train/* -o prior.fits --prior vk.fits --ridge 1e9 --no-heldout --no-mean-miss > learn_prior.log 2>&1 \
    || { cat learn_prior.log; fail "learn --prior"; }
head -c 8640 prior.fits | grep -aq "LRNPRIOR= 'vk.fits *'" || fail "prior.fits: no LRNPRIOR"
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --recon prior.fits --match science.fits \
    sci_p.fits -o spk_p.fits 2> speckles_p.log || { cat speckles_p.log; fail "speckles with the prior's map"; }
"$B" estimate sci_p.fits spk_p.fits -o halo_p.fits > /dev/null 2>&1 || fail "estimate (prior)"
"$B" pupil halo_p.fits -o pupil_p.fits --truth obs/truth.fits > pupil_p.log || fail "pupil (prior)"
ep=$(ncp_error pupil_p.log)
echo "cli_learn: learn --prior vk.fits --ridge 1e9: NCP error $ep nm (vk $ed nm)"
awk -v p="$ep" -v d="$ed" 'BEGIN { exit !(p > 0 && p < d + 0.3 && p > d - 0.3) }' || fail "--prior at 1e9: $ep nm, vk $ed nm"
# a space-time map of the same loops (their second layers drawn from a spread, not the
# observation's): learn records the loops' layers and slopes' correlation, and speckles prints
# both checks against the observation's telemetry, whose two layers (15 and 22 m/s) `wind`
# finds
"$B" learn train/* -o lagged.fits --lags 0,-4,4 --no-heldout > learn_lags.log 2>&1 || { cat learn_lags.log; fail "learn --lags"; }
grep -q "x 3 lags (0,-4,4)" learn_lags.log || { cat learn_lags.log; fail "learn --lags printed no lags"; }
# a space-time map is no prior
"$B" learn train/* -o bad.fits --prior lagged.fits --ridge 1 --no-heldout > bad.log 2>&1 && fail "a space-time prior accepted"
grep -q "lagged.fits: a space-time map (NLAGS 3); --prior takes a per-frame map" bad.log || { cat bad.log; fail "learn: the prior's message"; }
[ -e bad.fits ] && fail "learn left a map after a refused prior"
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --recon lagged.fits \
    -o spk_st.fits 2> speckles_st.log || { cat speckles_st.log; fail "speckles with a space-time map"; }
grep -q "given space-time reconstructor lagged.fits: 288 slopes x 3 lags" speckles_st.log \
    && grep -q "space-time map: the slopes' correlation, this telemetry's against the training loops'" speckles_st.log \
    && grep -q "space-time map: this telemetry's slopes show 2 frozen-flow layers" speckles_st.log \
    || { cat speckles_st.log; fail "speckles printed no check of the space-time map"; }
grep "space-time map" speckles_st.log | cut -c1-160
# the gain check on a learned space-time map (RECON = 'learned') refuses only a sign: its lag
# blocks' sum on a still wavefront is no convention's gain (a bright star's taught map had 2.03)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --recon lagged.fits \
    --recon-scale 3 -o spk_st3.fits 2> speckles_st3.log || { cat speckles_st3.log; fail "a learned space-time map x 3 refused"; }
grep -q "lagged.fits: 288 slopes x 3 lags x 217 actuators, scale 3, gain [2-9]" speckles_st3.log || { cat speckles_st3.log; fail "speckles: the x 3 map's gain"; }
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --recon lagged.fits \
    --recon-scale -1 -o spk_stm.fits 2> speckles_stm.log && fail "a learned space-time map of the other sign accepted"
grep -q "lagged.fits: gain -[0-9.]* on the model's interaction matrix after the scale given" speckles_stm.log \
    || { cat speckles_stm.log; fail "speckles: the sign's refusal"; }
[ -e spk_stm.fits ] && fail "speckles left a product after the sign's refusal"
# teach: the same rule in one command (wind -> loops at the layers found -> the space-time map
# and its checks -> the choice; the loops in taught.teach, the default work folder). Its two layers must be the observation's (15 and 22 m/s), its
# map the space-time one (neither check warns on loops of the same system), and through the
# whole path no worse than the default reconstructor by more than 10 %.
"$B" teach obs/slopes_0*.fits --system my.conf vib_amp=0.3 ao_modes=56 -o taught.fits --loops 4 --max-loops 4 > teach.log 2>&1 \
    || { cat teach.log; fail "teach"; }
grep -q "2 frozen-flow layers" teach.log && grep -q "chose the space-time map (neither check warned)" teach.log \
    || { cat teach.log; fail "teach: two layers and the space-time map expected"; }
awk '/^teach:   layer [12]: / { v[++n] = $4 } END { exit !(n == 2 && ((v[1] > 13.5 && v[1] < 16.5 && v[2] > 19.8 && v[2] < 24.2) ||
    (v[2] > 13.5 && v[2] < 16.5 && v[1] > 19.8 && v[1] < 24.2))) }' teach.log || { cat teach.log; fail "teach: the layers"; }
# the observation's file holds ~1780 frames: four loops that long would give the map (5 lags x
# 224 slopes = 1120 inputs) 6.4 frames per input; teach lengthens them to 10 (4 x 2800 frames)
grep -q "^teach: 4 loops simulated of 2800 WFS frames (lengthened from 17[0-9][0-9]: the map's 1120 inputs need 10 frames each)" \
    teach.log || { grep "loops simulated" teach.log; fail "teach: loops of 10 frames per map input expected"; }
# --max-loops 4: no more loops to add, so no learning curve measured (six solves of the map's
# normal equations saved; python/tests/test_realdata.py lets teach measure it and add loops)
grep -q "^teach: the space-time map's learning curve: not measured (at most 4 loops: no more to add)" \
    teach.log || { grep "learning curve" teach.log; fail "teach: the learning curve's line expected"; }
head -c 8640 taught.fits | grep -aq "NLAGS   =                    5" || fail "teach: taught.fits is no 5-lag cube"
head -c 8640 taught.fits | grep -aq "TEACHSEL= 'spacetime'" || fail "teach: the map's header should say it was chosen as such"
[ "$(ls -d taught.teach/loop_*/ | wc -l)" = 4 ] && [ -s taught.teach/spacetime.fits ] \
    || fail "teach: the loops or the map tried (in the default work folder taught.teach)"
# the description gives ao_modes (the observation's loop controls the simulator's 56 modes):
# used as given, no calibration loop (teach_files below finds it from the slopes)
grep -q "modal filter: ao_modes = 56, as given" teach.log && [ ! -d taught.teach/modes_00 ] \
    && head -c 11520 taught.fits | grep -aq "TEACHMSR= 'given" || { cat teach.log; fail "teach: ao_modes as given"; }
et=$(ncp_with taught.fits t timing.txt)
echo "cli_learn: teach: NCP error $et nm with the taught map, $ed nm with vk"
awk -v t="$et" -v d="$ed" 'BEGIN { exit !(t > 0 && t < 1.1 * d) }' || fail "taught $et nm against the default $ed nm"
# no description at all (teach_files, lib_learn.sh): through the whole path within 1 nm of the
# described teach
teach_files
echo "cli_learn: teach from the observation's files: $etf nm (described: $et nm; vk $ed nm)"
awk -v a="$etf" -v b="$et" 'BEGIN { exit !(a > 0 && a - b < 1 && b - a < 1) }' || fail "teach from files $etf nm against $et nm"
# the system from files needs both files; without any system teach says what it needs
"$B" teach obs/slopes_000.fits --science science.fits -o bad.fits > bad.log 2>&1 && fail "teach without --actuators"
grep -q "needs both --science and --actuators" bad.log || { cat bad.log; fail "teach: --science alone"; }
"$B" teach obs/slopes_000.fits -o bad.fits > bad.log 2>&1 && fail "teach without a system"
grep -q "needs the system: --science SCI.fits --actuators ACT.fits" bad.log || { cat bad.log; fail "teach: no system"; }
[ -e bad.fits ] && fail "teach left a map after a usage error"
"$B" learn obs -o bad.fits --curve --threads -1 > bad.log 2>&1 && fail "learn --threads -1 accepted"
grep -q -- "--threads must be 0 (the CPUs) to 4096, got -1" bad.log || { cat bad.log; fail "learn: --threads -1"; }
[ -e bad.fits ] && fail "learn left a map after a usage error"
# the loops described with ten times the slope noise: the correlation check warns, and with one
# layer found teach falls back to the per-frame map of the layer and random seconds. The
# observation's loop controls 36 modes, which teach finds from its slopes (within 15 %).
"$B" simulate my.conf nlayers=1 layer_frac=1 layer_speed=15 layer_dir=30 seed=5 ao_modes=36 -o obs1 --quiet > /dev/null 2>&1 \
    || fail "simulate the one-layer observation"
"$B" teach obs1/slopes_0*.fits --system my.conf slope_noise=3e-7 -o taught1.fits --work taught1 --loops 2 > teach1.log 2>&1 \
    || { cat teach1.log; fail "teach (one layer)"; }
grep -q "warning: .* frames apart this telemetry's slopes correlate" teach1.log \
    && grep -q "chose the per-frame map of the measured layer and random second layers" teach1.log \
    || { cat teach1.log; fail "teach: the correlation check should warn and the per-frame map be chosen"; }
head -c 8640 taught1.fits | grep -aq "NLAGS" && fail "teach: the per-frame map should hold no lags"
grep -q "the loops' slope_noise 3e-07 rad, as given$" teach1.log || { grep "white noise" teach1.log; fail "teach: slope_noise as given"; }
[ "$(ls -d taught1/mixed_*/ | wc -l)" = 2 ] || fail "teach: two loops of a random second layer expected"
awk '/modal filter from the slopes/ { for (i = 1; i <= NF; i++) if ($i == "ao_modes" && $(i + 1) == "=") k = $(i + 2) + 0 }
    END { exit !(k >= 31 && k <= 41) }' teach1.log || { cat teach1.log; fail "teach: the modal filter from the slopes (36)"; }
head -c 8640 taught1.fits | grep -aq "TEACHSEL= 'perframe_mixed'" && head -c 8640 taught1.fits | grep -aq "TEACHWRN=  *2 " \
    || fail "teach: the map's header should say the per-frame map of random seconds, the correlation check warning"
grep -q "the loops are zonal" teach1.log && { cat teach1.log; fail "teach: a modal loop taken for a zonal one"; }
# a zonal loop (ao_rcond: the truncated pseudo-inverse of the interaction matrix, every mode the
# sensor sees controlled) has no knee; teach's zonal calibration loops match its mode variances
# and the loops are zonal at the observation's cut or a neighbour (measured: 0.05 for 0.05)
"$B" simulate my.conf layer_speed=15,22 seed=9 ao_rcond=0.05 -o obsz --quiet > /dev/null 2>&1 || fail "simulate the zonal loop"
"$B" teach obsz/slopes_0*.fits --system my.conf -o taughtz.fits --work taughtz --loops 2 > teachz.log 2>&1 \
    || { cat teachz.log; fail "teach (zonal loop)"; }
grep -q "the loops are zonal, ao_rcond = 0.0[357]$" teachz.log && [ -d taughtz/zonal_05 ] \
    && head -c 11520 taughtz.fits | grep -aq "TEACHMSR= 'zonal" && head -c 11520 taughtz.fits | grep -aq "TEACHRCO=" \
    || { cat teachz.log; fail "teach: a zonal loop at the observation's cut (0.05) or a neighbour expected"; }
echo "cli_learn: zonal loop: $(grep -o 'zonal loops (ao_rcond:.*' teachz.log)"
# a system of another geometry than the telemetry's: refused, naming the file; no map left
"$B" teach obs1/slopes_000.fits --system my.conf nsub=16 -o bad.fits --work badw --loops 2 > bad.log 2>&1 \
    && fail "teach accepted a 16 x 16 system for 12 x 12 telemetry"
grep -q "obs1/slopes_000.fits: 288 slopes per WFS frame; the system's 16 x 16" bad.log || { cat bad.log; fail "teach: the message"; }
[ -e bad.fits ] && fail "teach left a map after failing"
[ -e badw ] && fail "teach left the work folder it made (empty) after refusing its input"
echo "cli_learn: ok"
