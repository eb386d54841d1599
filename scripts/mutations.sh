#!/usr/bin/env bash
# Mutation check for the anchor method, the cache's density rules, ray offsets, the glossy fit,
# watch mode's replay and checkpoints: applies each deliberate
# breakage kept in scripts/mutations/NAME.patch to the source, builds the tests, runs the
# tests that are meant to catch it, and reports CAUGHT (some test failed) or MISSED (all passed); the source is
# restored after each one, also on interrupt.
#
#   scripts/mutations.sh                 every mutation
#   scripts/mutations.sh d-max-4x ...    the named ones
#   MUTATION_TESTS="filter ..." scripts/mutations.sh NAME   other test filters
#
# The tests per mutation are listed below (the integration-test binary's name filters, or
# with "lib:" the library's unit tests); each patch's
# first lines say what it breaks. Needs a clean src/ (uncommitted changes there would be
# mixed into the mutants). Exit status: 0 when every mutation was caught, 1 otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."
# The mutants build in a target directory of their own, so that target/release keeps the
# binaries of the source as it is (the first run builds everything once).
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target/mutants}"

declare -A TESTS=(
  [no-reshoot]="anchor_faults anchors::"
  [frozen-li]="anchor_faults anchors::"
  [d-max-4x]="anchor_faults anchors::"
  [no-shadow-ray-reuse-check]="anchor_faults anchors::"
  [inverted-importance]="anchor_faults anchors::"
  [no-sample-records]="density::"
  [weber-never-removes]="density::"
  [lit-back-faces-enclosed]="density::"
  [no-neighbour-clamp]="density::"
  [ray-offsets-shrunk]="offsets::"
  [glossy-through-albedo]="glossy::a_rough_metal"
  [replay-without-ray-check]="watch::a_relight_that_replays"
  [replay-direct-without-keys]="watch::a_relight_that_replays"
  [replay-reads-without-key]="watch::a_relight_that_replays"
  [replay-emitters-without-pick-check]="watch::a_relight_that_replays"
  [slack-near-dynamic]="anchor_faults::a_plate"
  [slack-ignored]="density::a_moving_camera"
  [uncached-reads-without-albedo]="anchors::a_gather_no_record_covers"
  [reshoot-ray-test-short]="anchors::every_stratum"
  [spot-records-never-read]="density::samples_no_record_covers"
  [spot-records-dropped]="density::samples_no_record_covers"
  [batch-anchors-not-in-tree]="anchors::a_batch_links"
  [untouched-test-short]="anchors::kept_anchor_estimates"
  [dynamic-radiance-misplaced]="anchor_faults anchors::"
  [references-one-share]="anchors::"
  [relink-first-found]="anchors::anchors_link_their_nearest_photons"
  [retry-takes-fewer]="anchors::searches_bounded"
  [integration-untimed]="gi::uncached_samples_count"
  [shares-forget-made]="anchors::a_batch"
  [enclosed-placed-again]="density::a_fixed_camera"
  [anchor-direct-dropped]="photons::shadow_rays_at_gather"
  [first-hits-counted-twice]="photons::shadow_rays_at_gather"
  [anchors-wide-with-shadow-rays]="photons::shadow_rays_at_gather"
  [checkpoint-build-unchecked]="shot::a_foreign_checkpoint"
  [gather-shadow-rays-uncounted]="shot::shadow_rays_at_gather_hits_resume"
  [checkpoint-memory-uncounted]="hardening::checkpoints_count"
  [parts-finished-each]="anchors::gathering_a_batch"
  [parts-link-afresh]="anchors::gathering_a_batch"
  [gather-estimate-unparted]="hardening::gathering_counts"
  [dynamic-radiance-dropped]="anchor_faults anchors::"
  [gather-search-uncounted]="hardening::gathering_counts"
  [checkpoint-written-whole]="lib:checkpoint::"
  [checkpoint-read-whole]="lib:checkpoint::"
  [wide-pair-one-shear]="lib:accel::"
  [wide-boxes-one-child]="lib:accel::"
  [grid-last-lane-skipped]="lib:cache::"
  [placement-untimed]="gi::uncached_samples_count"
  [upkeep-untimed]="gi::uncached_samples_count"
  [group-photon-misplaced]="anchors::a_batch"
  [kd-spill-far-dropped]="lib:anchor::kdtree"
  [grouped-map-next-empty]="lib:photon::knn"
  [normal-table-bytes-swapped]="lib:color::"
  [exact-segment-wrong-side]="lib:interaction::"
  [search-buffers-not-swapped]="anchors::a_batch"
  [four-lanes-swapped]="lib:accel::"
  [faces-away-open-prims]="lib:visibility::tests"
  [faces-away-inside-sphere]="lib:visibility::tests"
  [cluster-cap-halved]="lib:visibility::tests"
  [cluster-tree-node-short]="lib:visibility::tests"
  [cluster-walk-skips-child]="lib:visibility::tests"
  [clusters-unsorted]="lib:visibility::tests"
  [camera-untimed]="gi::uncached_samples_count"
  [quarter-lanes-edge-dropped]="lib:visibility::tests"
  [quarter-lanes-rows-crossed]="lib:visibility::tests"
  [row-lanes-skip-widened]="lib:visibility::tests"
  [row-columns-one-sided]="lib:visibility::tests"
)
ORDER=(no-reshoot frozen-li d-max-4x no-shadow-ray-reuse-check inverted-importance
  no-sample-records weber-never-removes lit-back-faces-enclosed no-neighbour-clamp
  ray-offsets-shrunk glossy-through-albedo replay-without-ray-check replay-direct-without-keys
  replay-reads-without-key replay-emitters-without-pick-check slack-near-dynamic slack-ignored
  uncached-reads-without-albedo reshoot-ray-test-short spot-records-never-read spot-records-dropped
  batch-anchors-not-in-tree untouched-test-short dynamic-radiance-misplaced
  references-one-share relink-first-found retry-takes-fewer integration-untimed
  shares-forget-made enclosed-placed-again anchor-direct-dropped first-hits-counted-twice
  anchors-wide-with-shadow-rays checkpoint-build-unchecked gather-shadow-rays-uncounted
  checkpoint-memory-uncounted parts-finished-each parts-link-afresh
  gather-estimate-unparted dynamic-radiance-dropped gather-search-uncounted
  checkpoint-written-whole checkpoint-read-whole wide-pair-one-shear wide-boxes-one-child
  grid-last-lane-skipped placement-untimed upkeep-untimed group-photon-misplaced
  kd-spill-far-dropped grouped-map-next-empty normal-table-bytes-swapped exact-segment-wrong-side
  search-buffers-not-swapped four-lanes-swapped faces-away-open-prims faces-away-inside-sphere
  cluster-cap-halved cluster-tree-node-short cluster-walk-skips-child clusters-unsorted
  camera-untimed quarter-lanes-edge-dropped quarter-lanes-rows-crossed row-lanes-skip-widened
  row-columns-one-sided)

names=("$@")
[ ${#names[@]} -eq 0 ] && names=("${ORDER[@]}")

if ! git diff --quiet -- src; then
  echo "mutations.sh: src/ has uncommitted changes; commit or stash them first" >&2
  exit 2
fi

applied=""
restore() {
  if [ -n "$applied" ]; then
    git apply -R "$applied" && applied=""
  fi
}
trap restore EXIT
trap 'restore; exit 130' INT TERM

# Builds the integration-test binary (with "lib", the library's unit tests) and prints its
# path (empty if the build failed).
test_binary() {
  local target=(--test main) kind='"kind":["test"]'
  [ "${1:-}" = lib ] && target=(--lib) kind='"kind":["lib"]'
  cargo test --release "${target[@]}" --no-run --message-format=json 2>/dev/null |
    grep -F "$kind" | sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1
}

declare -A RESULT
missed=0
for name in "${names[@]}"; do
  patch="scripts/mutations/$name.patch"
  [ -f "$patch" ] || { echo "mutations.sh: no $patch" >&2; exit 2; }
  filters="${MUTATION_TESTS:-${TESTS[$name]:-anchor}}"
  # "lib:FILTER" runs the library's unit tests.
  suite=main
  case "$filters" in lib:*) suite=lib filters="${filters#lib:}" ;; esac
  echo "== $name: $(sed -n 's/^# //p' "$patch" | head -1)"
  git apply "$patch"
  applied="$patch"
  bin="$(test_binary "$suite")"
  [ -n "$bin" ] || { echo "mutations.sh: $name does not build" >&2; exit 2; }
  log="target/mutations/$name.log"
  mkdir -p target/mutations
  # shellcheck disable=SC2086
  if "$bin" $filters --test-threads 2 >"$log" 2>&1; then
    RESULT[$name]="MISSED"
    missed=$((missed + 1))
  else
    RESULT[$name]="CAUGHT by $(sed -n 's/^    \([a-z_]*::[^ ]*\)$/\1/p' "$log" | sort -u | tr '\n' ' ')"
  fi
  echo "   ${RESULT[$name]} (log: $log)"
  restore
done

echo
echo "mutation                      result"
for name in "${names[@]}"; do
  printf '%-29s %s\n' "$name" "${RESULT[$name]}"
done
[ "$missed" -eq 0 ]
